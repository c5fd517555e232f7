"""What a record of the store says of itself beside its key (budget, seeds, method, environment),
checked against the components its key was computed from. Listings show and filter on these
fields, and a key says nothing of them unless they agree with its components: a manifest
relabelled after its key was made (a smoke run of one spec shown as a paper run of another) is
refused by `esr import` and named by `esr verify`."""

from __future__ import annotations

from esr_cli.storage.store import RUN_KIND


def _part(value: object, name: str) -> dict:
    part = value.get(name) if isinstance(value, dict) else None
    return part if isinstance(part, dict) else {}


def keyed_labels(record: dict) -> dict:
    """The labels `record`'s key components fix: the budget where its components name one; for a
    run, also its seeds, method and environment (from the spec it was keyed by)."""
    components = _part(record, "key_components")
    said = {"budget": components["budget"]} if "budget" in components else {}
    if record.get("kind") == RUN_KIND and "spec" in components:
        spec = _part(components, "spec")
        said.update(seeds=_part(spec, "train").get("seeds"), method=_part(spec, "method").get("kind"),
                    env=_part(spec, "env").get("kind"))
    return said


def labels_problem(record: dict, name: str) -> str | None:
    """Why a label of `record` (a manifest or a pending.json, file `name`) is not what its key
    components say, or None. A label the record leaves out is not checked (esr writes every one
    of them; an older esr wrote fewer)."""
    wrong = [field for field, want in keyed_labels(record).items() if field in record and record[field] != want]
    if not wrong:
        return None
    return (f"{name} names its {' and '.join(wrong)} otherwise than its key components do: "
            "the artifact was relabelled after its key was made")
