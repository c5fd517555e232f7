"""The pages of a study between its episodes (participant id, consent, instructions, a
questionnaire, the end), as both front ends show them, and the checks of what comes back.

A front end's `ask(page)` shows the page and returns the person's reply, {"button": name,
"answers": {item id: value}}, or None when the tab or terminal went away; a page without
buttons (the end) is only shown ({}). Replies are checked here, never trusted to the front end:
a browser page can send anything.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from esr_cli.play.study import MAX_TEXT_ANSWER, PARTICIPANT_RULE, blocks_of, participant_problem


@dataclass(frozen=True)
class Button:
    name: str  # what the reply says
    key: str  # the terminal's key for it (a name of game.KEYS or a letter)
    text: str


@dataclass(frozen=True)
class Page:
    kind: str  # participant, consent, instructions, questionnaire, end
    title: str
    blocks: tuple[tuple[str, str], ...] = ()  # (h | p | li, text): shown as text, never as markup
    items: tuple[dict, ...] = ()  # the questions: {id, kind (likert, text, participant), text, ...}
    buttons: tuple[Button, ...] = ()
    code: str = ""  # a completion code, shown large
    error: str = ""  # what was wrong with the last reply

    def message(self) -> dict:
        """The page as the browser's script draws it."""
        return {"kind": self.kind, "title": self.title, "blocks": [list(b) for b in self.blocks],
                "items": list(self.items), "buttons": [{"name": b.name, "text": b.text} for b in self.buttons],
                "code": self.code, "error": self.error}


CONTINUE = Button("continue", "space", "Continue")
PARTICIPANT_ITEM = {"id": "participant", "kind": "participant", "text": "Your participant id", "max_chars": 64,
                    "required": True}


def participant_page() -> Page:
    return Page("participant", "Welcome", (("p", "Please enter your participant id."),), (PARTICIPANT_ITEM,),
                (CONTINUE,))


def consent_page(text: str) -> Page:
    return Page("consent", "Consent", tuple(blocks_of(text)), (),
                (Button("agree", "y", "I agree"), Button("decline", "n", "I do not agree")))


def instructions_page(text: str) -> Page:
    return Page("instructions", "Instructions", tuple(blocks_of(text)), (), (Button("continue", "space", "Start"),))


def questionnaire_page(robot: str, items: tuple[dict, ...]) -> Page:
    return Page("questionnaire", f"Questions about {robot}", (("p", f"You have just played with {robot}."),), items,
                (Button("submit", "enter", "Submit"),))


def end_page(text: str, code: str | None) -> Page:
    blocks = tuple(blocks_of(text)) + ((("p", "Your completion code:"),) if code else ())
    return Page("end", "Thank you", blocks, code=code or "")


def declined_page() -> Page:
    return Page("end", "Thank you", (("p", "You did not agree to take part, so the study ends here. Nothing about "
                                           "you has been recorded, only that consent was declined."),))


def with_error(page: Page, error: str) -> Page:
    return replace(page, error=error)


# ---------------------------------------------------------------- checking replies
def check_item(item: dict, value) -> tuple[object, str]:
    """(the answer as stored, "") or (None, what is wrong with it)."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None, f"please answer: {item['text']}" if item.get("required") else ""
    if item["kind"] == "likert":
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= item["scale"]:
            return None, f"choose a number from 1 to {item['scale']}: {item['text']}"
        return value, ""
    if not isinstance(value, str):
        return None, f"expected text: {item['text']}"
    value = value.strip()
    if len(value) > item.get("max_chars", MAX_TEXT_ANSWER):
        return None, f"at most {item['max_chars']} characters (this has {len(value)}): {item['text']}"
    if item["kind"] == "participant" and participant_problem(value):
        return None, f"a participant id is {PARTICIPANT_RULE}"
    return value, ""


def check_answers(items: tuple[dict, ...], answers: dict) -> tuple[dict, str]:
    """({item id: answer} for every item, None where unanswered, "") or ({}, the first problem)."""
    clean = {}
    for item in items:
        clean[item["id"]], problem = check_item(item, answers.get(item["id"]))
        if problem:
            return {}, problem
    return clean, ""


def item_dicts(questionnaire) -> tuple[dict, ...]:
    """A study's questionnaire items (pydantic models) as the pages carry them."""
    return tuple(item.model_dump(mode="json") for item in questionnaire)

