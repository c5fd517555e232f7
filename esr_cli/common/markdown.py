"""Text from a store (a device's name, as a manifest records it) written into a markdown page
as the text it is: no character of it can open a code span, a link, an HTML tag or comment, or
end a table cell."""

from __future__ import annotations

# The characters that start markdown or HTML structure inside a line; each is escaped with a
# backslash, which CommonMark allows before any ASCII punctuation and renders as the character.
STRUCTURAL = "\\`<>[]|!*_~"


def plain_text(text: str) -> str:
    """`text` (already free of control characters) escaped so that it renders as written."""
    return "".join("\\" + c if c in STRUCTURAL else c for c in text)
