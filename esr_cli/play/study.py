"""A user study as a file (`esr play --study STUDY.yaml`, docs/play.md): who plays with which
robots, what they read first, what they are asked after each robot, and the code they get at
the end.

    name: grid_pilot
    environment: ../grid_2.yaml          # the spec the robots were trained with (relative to this file)
    budget: quick                        # and its budget (and `set:` overrides), as for `esr play`
    robots:                              # a label the participant never sees, and a run (key or prefix) or random
      - {label: baseline, run: random}
      - {label: esr, run: 3f0c9a}
    episodes_per_robot: 2
    order: counterbalanced               # or fixed: the order written here
    practice_episodes: 1                 # with a random robot, kept out of the results
    consent: consent.md                  # plain text or simple markdown, shown escaped
    instructions: instructions.md
    questionnaire:                       # asked after each robot's episodes
      - {id: helpful, kind: likert, text: The robot helped me., scale: 7, anchors: [disagree, agree]}
      - {id: comments, kind: text, text: Anything else?, max_chars: 300}
    completion: {generated: true}        # or {code: C0DE12}: the end page's completion code

The file is read with the bounded YAML reader and validated before any work; every mistake is a
`StudyError`: one line naming the file, the key path and the problem (exit 2). The consent and
instruction files must lie in the study file's folder (a study file from elsewhere must not put
~/.ssh/id_rsa on a participant's screen) and are read bounded.
"""

from __future__ import annotations

import json
import re
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from esr_cli.common import bounded_files, specs, yamlio
from esr_cli.model import spec as spec_model
from esr_cli.storage.store import digest_bytes

MAX_TEXT_FILE_BYTES = 64 * 1024  # a consent form or instructions: a few pages at most
# A free-text answer travels in one websocket message of at most 4 KiB (esr_cli/play/web.py);
# 500 characters fit even when every one is escaped in JSON (6 bytes).
MAX_TEXT_ANSWER = 500
MAX_ITEMS = 50
MAX_ROBOTS = 26  # robot A to robot Z
NAME = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"
RUN = r"^(random|[0-9a-f]{4,32})$"
PARTICIPANT = re.compile(NAME)
PARTICIPANT_RULE = "1 to 64 letters, digits, '_', '.' or '-', starting with a letter or digit"


class StudyError(specs.SpecError):
    """A study file that cannot be used; `str()` is one line naming file, key path and problem."""

    def one_line(self) -> str:
        return f"bad study file: {self}"


def participant_problem(participant: str) -> str:
    """Why `participant` is not a usable id ("" when it is): ids come from a command line, a
    URL or a form, and end up in file names of exports and in tables."""
    return "" if PARTICIPANT.fullmatch(participant or "") else f"a participant id is {PARTICIPANT_RULE}"


def _one_line_text(v: str) -> str:
    if any(unicodedata.category(c).startswith("C") for c in v):
        raise ValueError("control characters (a newline, a tab, an escape) are not allowed here")
    return v


Line = Annotated[str, Field(min_length=1, max_length=1000), AfterValidator(_one_line_text)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class LikertItem(_Model):
    id: str = Field(..., pattern=NAME)
    kind: Literal["likert"]
    text: Line
    scale: spec_model.Int = Field(..., ge=2, le=11, description="points on the scale, 1 to scale")
    anchors: tuple[Annotated[Line, Field(max_length=100)], ...] = Field(
        ..., description="the words at the two ends, or one for each point")
    required: bool = True

    @model_validator(mode="after")
    def _anchors_fit(self):
        if len(self.anchors) not in (2, self.scale):
            raise ValueError(f"anchors: give 2 (the ends of the scale) or {self.scale} (one per point), "
                             f"not {len(self.anchors)}")
        return self


class TextItem(_Model):
    id: str = Field(..., pattern=NAME)
    kind: Literal["text"]
    text: Line
    max_chars: spec_model.Int = Field(MAX_TEXT_ANSWER, ge=1, le=MAX_TEXT_ANSWER)
    required: bool = False


Item = Annotated[Union[LikertItem, TextItem], Field(discriminator="kind")]


class RobotEntry(_Model):
    label: str = Field(..., pattern=NAME, description="the researcher's name for it; participants see robot A, B, ...")
    run: str = Field(..., pattern=RUN, description="a trained run's key or key prefix, or random")


class Completion(_Model):
    code: Optional[str] = Field(None, pattern=r"^[A-Za-z0-9_\-]{1,40}$", description="shown to every participant")
    generated: bool = Field(False, description="a new code for each participant, stored with their session")
    text: Line = "Thank you for taking part."

    @model_validator(mode="after")
    def _one_code(self):
        if (self.code is None) == (not self.generated):
            raise ValueError("give either `code: ...` (the same for everyone) or `generated: true` (one per participant)")
        return self


class StudyModel(_Model):
    name: str = Field(..., pattern=NAME)
    environment: str = Field(..., min_length=1, max_length=1000, description="the spec file the robots were trained with")
    budget: str = "paper"
    set: dict[str, Any] = Field(default_factory=dict, description="overrides of the spec, as --set gives them")
    robots: tuple[RobotEntry, ...] = Field(..., min_length=1, max_length=MAX_ROBOTS)
    episodes_per_robot: spec_model.Int = Field(..., ge=1, le=100)
    order: Literal["counterbalanced", "fixed"] = "counterbalanced"
    practice_episodes: spec_model.Int = Field(1, ge=0, le=20)
    consent: str = Field(..., min_length=1, max_length=1000)
    instructions: str = Field(..., min_length=1, max_length=1000)
    questionnaire: tuple[Item, ...] = Field((), max_length=MAX_ITEMS)
    fps: spec_model.Float = Field(6.0, ge=0.5, le=60, description="Overcooked: steps per second")
    countdown: spec_model.Float = Field(3.0, ge=0, le=30)
    seed: spec_model.Int = Field(0, ge=0, le=spec_model.MAX_SEED - 200)
    seed_index: spec_model.Int = Field(0, ge=0)
    completion: Completion

    @field_validator("budget")
    @classmethod
    def _known_budget(cls, v):
        if v not in spec_model.BUDGETS:
            raise ValueError(f"unknown budget {v!r}; known: {', '.join(spec_model.BUDGETS)}")
        return v

    @field_validator("set")
    @classmethod
    def _key_paths(cls, v):
        for dotted in v:
            if not all(dotted.split(".")):
                raise ValueError(f"{dotted!r} is not a key path like env.blocks")
        if twice := specs.set_twice((k, k, value) for k, value in v.items()):
            raise ValueError(twice)
        return v

    @field_validator("robots")
    @classmethod
    def _labels_once(cls, v):
        return _once(v, "label", "robot label")

    @field_validator("questionnaire")
    @classmethod
    def _ids_once(cls, v):
        return _once(v, "id", "item id")


def _once(entries, field: str, what: str):
    seen = set()
    for entry in entries:
        name = getattr(entry, field)
        if name in seen:
            raise ValueError(f"the {what} {name!r} is used twice")
        seen.add(name)
    return entries


@dataclass(frozen=True)
class Study:
    """A validated study: the file's fields, the spec its robots play, and its texts."""

    path: Path
    model: StudyModel
    spec: Any  # the validated spec of `environment` (budget and `set` applied)
    environment: Path
    consent: str
    instructions: str
    digest: str  # of the study file and its texts: which version a session ran

    @property
    def name(self) -> str:
        return self.model.name

    @property
    def sets(self) -> list[str]:
        """`set:` as --set texts (JSON is YAML: each value reads back exactly)."""
        return [f"{k}={json.dumps(v, separators=(',', ':'))}" for k, v in self.model.set.items()]


def load_study(path: str | Path) -> Study:
    """The study file at `path`, validated with its spec and texts; raises StudyError."""
    source = str(path)
    try:
        raw = yamlio.read(path)
    except yamlio.YamlInputError as e:
        raise StudyError(source, "", str(e)) from None
    if not isinstance(raw, dict):
        raise StudyError(source, "", "the top level must be a mapping of the study's keys (name, environment, robots, ...)")
    model = validate(raw, source)
    folder = Path(path).resolve().parent
    consent = read_text(folder, model.consent, "consent", source)
    instructions = read_text(folder, model.instructions, "instructions", source)
    environment = folder / model.environment
    if not environment.is_file():
        raise StudyError(source, "environment", f"no spec file {model.environment!r} (relative to the study file)")
    study = Study(Path(path), model, None, environment, consent, instructions, "")
    try:
        spec = specs.load(environment, model.budget, study.sets)
    except specs.SpecError as e:
        raise StudyError(source, "environment", str(e)) from None
    texts = json.dumps([model.model_dump(mode="json"), consent, instructions], sort_keys=True)
    return Study(Path(path), model, spec, environment, consent, instructions, digest_bytes(texts.encode()))


def validate(raw: dict, source: str) -> StudyModel:
    try:
        return StudyModel.model_validate(raw)
    except ValidationError as e:
        err, msg = specs.first_problem(e)
        loc = tuple(err["loc"])
        if err["type"] == "extra_forbidden":
            msg += specs.did_you_mean(loc[-1], _names_at(loc))
        elif err["type"] == "union_tag_invalid":
            msg = f"kind {err.get('ctx', {}).get('tag')!r} is not one of likert, text"
        elif err["type"] == "union_tag_not_found":
            msg = "needs a `kind`: likert or text"
        elif err["type"] == "string_pattern_mismatch":
            rule = PATTERN_RULES.get(loc[-1], f"a name here is {PARTICIPANT_RULE}")
            msg = f"{str(err['input'])[:40]!r}: {rule}"
        raise StudyError(source, _study_path(loc), msg + specs.other_problems(e, _study_path)) from None


def _study_path(loc: tuple) -> str:
    """A location as the study file's key path (a questionnaire item's kind tag left out)."""
    return yamlio.key_path(loc, lambda i, part: i == 2 and loc[0] == "questionnaire" and part in ITEM_MODELS)


ITEM_MODELS = {"likert": LikertItem, "text": TextItem}
PATTERN_RULES = {"run": "a run's key or key prefix (4 to 32 hex digits), or random",
                 "code": "a completion code is 1 to 40 letters, digits, '_' or '-'"}


def _names_at(loc: tuple) -> list[str]:
    """The keys valid where an unknown key `loc[-1]` was found."""
    parent = [p for p in loc[:-1] if p not in ITEM_MODELS]
    if not parent:
        return list(StudyModel.model_fields)
    models = {"robots": RobotEntry, "completion": Completion}
    if parent[0] == "questionnaire" and len(loc) >= 3:
        return list(ITEM_MODELS.get(str(loc[2]), LikertItem).model_fields)
    return list(models[parent[0]].model_fields) if parent[0] in models else []


def read_text(folder: Path, name: str, key: str, source: str) -> str:
    """A text shown to participants: a file in the study's folder (no path out of it, symbolic
    links included), at most MAX_TEXT_FILE_BYTES of UTF-8 without control characters."""
    try:
        path = (folder / name).resolve()
    except (OSError, RuntimeError, ValueError) as e:
        raise StudyError(source, key, f"cannot follow {name[:60]!r}: {e}") from None
    if not path.is_relative_to(folder):
        raise StudyError(source, key, f"{name[:60]!r} is outside the study file's folder: texts shown to "
                                      "participants must lie beside the study file")
    if not path.is_file():
        raise StudyError(source, key, f"no file {name[:60]!r} in the study file's folder")
    try:  # `path` is resolved: no link is left to follow
        data = bounded_files.read_bytes(path, MAX_TEXT_FILE_BYTES, follow_links=True)
    except bounded_files.UnreadableInput as e:
        raise StudyError(source, key, f"{name[:60]}: {e}") from None
    except OSError as e:
        raise StudyError(source, key, f"cannot read {name[:60]}: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8").replace("\r\n", "\n")
    except UnicodeDecodeError:
        raise StudyError(source, key, f"{name[:60]} is not UTF-8 text") from None
    bad = next((i for i, c in enumerate(text) if c not in "\n\t" and unicodedata.category(c).startswith("C")), None)
    if bad is not None:
        raise StudyError(source, key, f"{name[:60]} line {text.count(chr(10), 0, bad) + 1}: a control character "
                                      f"{text[bad].encode('unicode_escape').decode()}; only text, newlines and tabs")
    if not text.strip():
        raise StudyError(source, key, f"{name[:60]} is empty")
    return text


def blocks_of(text: str) -> list[tuple[str, str]]:
    """Simple markdown as (kind, text) blocks, never as markup: `# heading` -> ("h", ...),
    `- item` or `* item` -> ("li", ...) with the lines that follow it, other lines joined into
    paragraphs ("p", ...); a blank line ends a paragraph or an item."""
    blocks, open_block = [], False
    for line in text.splitlines():
        line = " ".join(line.split())
        if line.startswith("#"):
            blocks.append(("h", line.lstrip("#").strip()))
            open_block = False
        elif line[:2] in ("- ", "* "):
            blocks.append(("li", line[2:]))
            open_block = True
        elif line and open_block:
            blocks[-1] = (blocks[-1][0], f"{blocks[-1][1]} {line}")
        elif line:
            blocks.append(("p", line))
            open_block = True
        else:
            open_block = False
    return blocks
