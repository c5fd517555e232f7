"""Reading JSON-lines files that are appended as work goes (metrics, played steps)."""

from __future__ import annotations

import json
from pathlib import Path


def read_jsonl(path: Path) -> list[dict]:
    """One dict per line; [] where the file does not exist yet. A line cut short by a kill ends
    the reading: everything after it is untrusted."""
    path = Path(path)
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return rows
