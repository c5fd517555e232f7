"""Experiment specs: YAML -> validated, frozen pydantic models.

Order of operations (see docs/specs.md):
  1. read the YAML file (unreadable or missing files are spec errors);
  2. apply the chosen budget's overrides (`budgets:` in the file, else the defaults below);
  3. apply `--set key.path=value` overrides from the command line;
  4. validate the result (unknown keys, types, ranges, cross-field rules).
Every failure raises `SpecError` naming the file, the key path and the problem.
"""

from __future__ import annotations

import copy
import json
import difflib
import re
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import yaml
from pydantic import ValidationError

from esr_cli.common import inert_fields, ppo_batch, yamlio
from esr_cli.common.failures import Failure
from esr_cli.model.spec import BUDGETS, HUMAN_PRESETS, KIND_MODELS, BCHumanSpec, Spec

# Budget overrides used when a spec does not define its own `budgets:` entry for that budget.
# `paper` is the spec as written. `quick` shows learning in minutes on a laptop CPU; `smoke`
# exercises every code path in seconds (tests).
# In 150 epochs the paper's settings never learn (docs/results.md): at the paper's
# representation rate (1e-4) the representations carry no information yet when the dual step
# has already made the robot's policy near-deterministic, and a policy that leaves the cornered
# human trapped produces no data that could teach otherwise. `quick` therefore starts with 20
# epochs of a uniformly acting robot (every update runs; SAC's start steps) and learns the
# representations 10x faster. Both apply only to kinds that have those fields.
DEFAULT_BUDGETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "quick": {
        "train.epochs": 150,
        "train.seeds": 1,
        "train.chunk_epochs": 10,
        "learner.warmup_epochs": 20,
        "method.repr_lr": 1e-3,
    },
    "smoke": {
        "train.epochs": 2,
        "train.num_envs": 4,
        "train.seeds": 1,
        "train.chunk_epochs": 1,
        "learner.updates_per_epoch": 3,
        "learner.dual_updates_per_epoch": 3,
        "learner.batch_size": 16,
        "method.repr_updates_per_epoch": 3,
        "method.updates_per_epoch": 3,
        "eval.episodes": 2,
    },
}



# A validator may quote the number it refuses (`9,999,... seeds`); one of hundreds of digits is
# named by its length instead, so that the message stays one readable line. Only a number written
# with thousands separators (as validators write them) or a bare run of digits standing alone
# counts: a compact list (`[100,101,...]`) or a path's digits are left as they are.
_LONG_NUMBER = re.compile(r"(?<![\w,./\[])(?:\d{1,3}(?:,\d{3}){8,}|\d{25,})(?![\w,./\]])")


def numbers_by_length(text: str) -> str:
    """A validator's message with each number of more than 24 digits replaced by its length."""
    return _LONG_NUMBER.sub(lambda m: f"(a number of {sum(c.isdigit() for c in m.group()):,} digits)", text)


MAX_SHOWN_OVERRIDE = 80


def shown_override(text: str) -> str:
    """A --set as an error names it: as typed, or its start and length when it is long."""
    return text if len(text) <= MAX_SHOWN_OVERRIDE else f"{text[:48]}... ({len(text):,} characters)"


class SpecError(Failure):
    """A spec that cannot be used. `str()` is one line naming file, key path and problem."""

    exit_code = 2

    def one_line(self) -> str:
        return f"bad spec: {self}"

    def __init__(self, source: str, path: str, problem: str):
        self.source, self.path, self.problem = source, path, problem
        where = f"{source}: " if source else ""
        key = f"{path}: " if path else ""
        super().__init__(f"{where}{key}{problem}")



# ---------------------------------------------------------------- loading
def _set_path(tree: dict, dotted: str, value: Any, source: str, within: str = "") -> None:
    """Set `dotted` (a key path inside the section `within`, when a mapping sets a section's keys)."""
    parts = dotted.split(".")
    if not all(parts):
        raise SpecError(source, within + dotted if dotted else f"{within}(an empty key)", "malformed key path")
    node = tree
    for i, p in enumerate(parts[:-1]):
        nxt = node.get(p)
        if nxt is None:
            nxt = node[p] = {}
        if not isinstance(nxt, dict):
            raise SpecError(source, within + ".".join(parts[: i + 1]), "is not a section, cannot set a key inside it")
        node = nxt
    old = node.get(parts[-1])
    if isinstance(value, dict) and isinstance(old, dict):
        # `train={epochs: 5}` means `train.epochs=5`: a mapping sets the keys it names and keeps
        # the section's others, as a YAML file's own section would not
        for key, item in value.items():
            _set_path(old, str(key), item, source, f"{within}{dotted}.")
        return
    node[parts[-1]] = value


def _fields_set(dotted: str, value: Any) -> Iterator[str]:
    """The fields one entry of a mapping of overrides sets: a mapping value sets the keys it names
    (walked without recursion: a value may nest as deep as its YAML allows)."""
    todo = [(dotted, value)]
    while todo:
        path, item = todo.pop()
        section, _, field = path.rpartition(".")
        if path in KIND_MODELS and isinstance(item, dict) and "kind" in item:
            yield path  # another kind starts the section again (`_switch_kind`): all of it is set
        elif field == "kind" and section in KIND_MODELS:
            yield section
        elif isinstance(item, dict) and item:
            todo += [(f"{path}.{key}", inner) for key, inner in reversed(item.items())]
        else:
            yield path


def set_twice(entries: Iterable[tuple[str, str, Any]]) -> str | None:
    """Where one mapping (or a suite's `set` beside its `grid`) sets one field twice, as
    `train: {epochs: 2}` beside `train.epochs: 9`, or a section and a key inside it: which of
    them would win depends only on the order they are written in. entries: (how each is
    named, its key path, its value); -> the problem in words, None if there is none. Each
    field costs its depth in lookups, however many entries there are."""
    by_field: dict[str, str] = {}  # each field set -> the entry that set it first
    above: dict[str, str] = {}  # each section holding a field set -> the entry that set it first
    for name, dotted, value in entries:
        for field in _fields_set(str(dotted), value):
            parts = field.split(".")
            sections = [".".join(parts[:i]) for i in range(1, len(parts))]
            clash = next(((f, by_field[f]) for f in (*sections, field) if by_field.get(f, name) != name), None)
            if clash is None and above.get(field, name) != name:
                clash = (field, above[field])
            if clash:
                return (f"{clash[1]} and {name} both set {clash[0]}: keep one (which would win depends only on "
                        "the order they are written in)")
            by_field.setdefault(field, name)
            for section in sections:
                above.setdefault(section, name)
    return None


def replaced_later(earlier: Iterable[tuple[str, str, Any]], later: Iterable[tuple[str, str, Any]]) -> str | None:
    """Where a mapping applied after another (a suite's `grid` after a `set`) sets a field the
    earlier one sets, or the whole section holding it, so that the earlier value never counts;
    a later field inside a section the earlier one starts (a kind, then its fields) refines it
    and is fine. Entries as set_twice takes them; -> the problem in words, None if none."""
    by_field: dict[str, str] = {}
    for name, dotted, value in earlier:
        for field in _fields_set(str(dotted), value):
            by_field.setdefault(field, name)
            parts = field.split(".")
            for i in range(1, len(parts)):  # a later value for a section holding it replaces it too
                by_field.setdefault(".".join(parts[:i]) + ".*", name)
    for name, dotted, value in later:
        for field in _fields_set(str(dotted), value):
            if (earlier_name := by_field.get(field) or by_field.get(field + ".*")) is not None:
                return (f"{name} replaces what {earlier_name} sets ({field}), which then never counts: keep one")
    return None


def _kind_has_field(tree: dict, dotted: str) -> bool:
    section, _, field = dotted.partition(".")
    if section not in KIND_MODELS:
        return True
    kind = (tree.get(section) or {}).get("kind") if isinstance(tree.get(section), dict) else None
    model = KIND_MODELS[section].get(kind) if isinstance(kind, str) else None  # a bad kind is validation's to name
    return model is None or field.split(".")[0] in model.model_fields


def parse_override(text: str) -> tuple[str, Any]:
    """`key.path=value` -> (path, YAML-parsed value)."""
    if "=" not in text:
        raise SpecError("--set", text, "expected key.path=value")
    path, raw = text.split("=", 1)
    if not path.strip():
        raise SpecError("--set", text[:60], "no key path before '=': expected key.path=value")
    if re.fullmatch(r"[^\[\]]+(\[\s*-?\d+\s*\])+", path.strip()):  # train.seeds[0]
        name = path.split("[")[0].strip()
        raise SpecError("--set", path.strip(), f"a list is set whole, not item by item: --set {name}=[...]")
    if "[" in path or "]" in path or not all(_FIELD_NAME.fullmatch(p) for p in path.strip().split(".") if p):
        # (`train.epochs+=5`, `train. epochs=5`: named here, as typed, not later as a spec file's unknown key)
        raise SpecError("--set", path.strip(), "not a key path like train.seeds (field names and dots)")
    if len(raw) > MAX_OVERRIDE_CHARS:
        raise SpecError("--set", path, f"value is {len(raw):,} characters long; at most {MAX_OVERRIDE_CHARS:,}")
    try:
        value = yamlio.parse(raw) if raw.strip() else ""
    except yamlio.YamlInputError as e:
        raise SpecError("--set", path, f"value is not valid YAML: {e}") from None
    return path.strip(), value


MAX_OVERRIDE_CHARS = 10_000
_FIELD_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")  # a hyphen passes: `repr-dim` gets its did-you-mean


# How pydantic names a validator or type in an error's location (`function-after[...]`,
# `list[int]`); a key the user wrote is kept even with a '[' in it.
_VALIDATOR_TAG = re.compile(r"[a-z][a-z0-9_-]*\[.*\]", re.S)


def _is_tag(i: int, part: object, loc: tuple) -> bool:
    """pydantic's discriminated-union and validator tags (`method.esr.x`), which are not key paths."""
    return (i == 1 and loc[0] in KIND_MODELS and part in KIND_MODELS[loc[0]]) or _VALIDATOR_TAG.fullmatch(str(part)) is not None


def _spec_path(loc: tuple, last_is_key: bool = False) -> str:
    """A location as the spec's key path (kind and validator tags left out)."""
    return yamlio.key_path(loc, lambda i, part: _is_tag(i, part, loc), last_is_key)


SECTIONS_WITHOUT_KINDS = ("network", "learner", "train", "eval")


def _valid_names(loc: tuple) -> list[str]:
    """The field names valid where an unknown key `loc[-1]` was found."""
    parent = loc[:-1]
    if not parent:
        return list(Spec.model_fields)
    section = parent[0]
    if section in KIND_MODELS and len(parent) >= 2:
        model = KIND_MODELS[section].get(parent[1])
        return list(model.model_fields) if model else []
    if section in SECTIONS_WITHOUT_KINDS and len(parent) == 1:
        return list(Spec.model_fields[section].annotation.model_fields)
    return []


def did_you_mean(name, known) -> str:
    """"; did you mean `KEY`?" naming the known key closest to a misspelt `name`, else ""."""
    close = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.6)
    return f"; did you mean `{close[0]}`?" if close else ""


def first_problem(e: ValidationError) -> tuple[dict, str]:
    """The mistake to name first and its message in plain words (no pydantic prefix or URL):
    an unknown key first (a typo usually also makes a required key 'missing', which is its
    consequence), then anything else in pydantic's order. Specs, suites and slurm options share it."""
    errors = e.errors()
    err = ([x for x in errors if x["type"] == "extra_forbidden"] or errors)[0]
    msg = err["msg"]
    if err["type"] == "extra_forbidden":
        msg = "unknown key"
    elif err["type"] == "missing":
        msg = "missing: this key is required"
    elif msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    elif err["type"] in ("model_attributes_type", "dict_type", "model_type"):
        msg = "expected a section (a mapping of keys), got " + (
            "an empty value (null)" if err["input"] is None else _described(err["input"]))
    elif err["type"] == "bool_type":
        msg = "expected true or false"
    elif err["type"] == "string_type" and isinstance(err["input"], (int, float)):
        msg = f"expected text, got {_described(err['input'])}: write it in quotes to mean the text"
    elif err.get("input", ...) is None and err["type"].endswith("_type"):
        msg = "the value is empty (null): write one, or leave the key out for its default"
    elif err["type"] in ("tuple_type", "list_type"):
        msg = f"expected a list, e.g. [a, b], got {_described(err['input'])}"
    elif err["type"] == "int_parsing_size" or (err["type"] in ("float_type", "float_parsing")
                                               and isinstance(err.get("input"), int) and not isinstance(err["input"], bool)):
        msg = "the number is far too large for this setting"
    return err, numbers_by_length(msg)


def _described(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    if isinstance(value, (int, float)):
        return f"the number {value!r:.40}"
    if isinstance(value, str):
        return f"the text {value[:40]!r}"
    return f"a {'mapping' if isinstance(value, dict) else type(value).__name__}"


SHOWN_PLACES = 3


def other_problems(e: ValidationError, where: Callable[[tuple], str] = yamlio.key_path) -> str:
    """' (and N more problem(s), at A, B)' after the first problem's message, or nothing: where
    the others are (`where` writes a location as the message's key path; at most SHOWN_PLACES),
    so that one reading names every key to mend."""
    errors = e.errors()
    if len(errors) < 2:
        return ""
    first = where(tuple(first_problem(e)[0]["loc"]))
    places = list(dict.fromkeys(where(tuple(x["loc"])) for x in errors))
    places.remove(first)
    shown = ", ".join(p or "the top level" for p in places[:SHOWN_PLACES]) + (", ..." if len(places) > SHOWN_PLACES else "")
    return f" (and {len(errors) - 1} more problem(s), at {shown})" if places else f" (and {len(errors) - 1} more problem(s) there)"


def _not_a_kind(kind, kinds) -> str:
    return f"kind {shown_override(repr(kind))} is not one of {', '.join(kinds)}"


def _without_conv_widths(human: Any) -> Any:
    """A BC human of network conv refuses `hidden` (the MLP's widths) written at all. A spec
    written out in full, as a run's spec.yaml is, writes it at its default, which says nothing
    (every field at its default passes, docs/specs.md): that one is left out."""
    if not isinstance(human, dict):
        return human
    default = list(BCHumanSpec.model_fields["hidden"].default)
    if human.get("network") == "conv" and isinstance(human.get("hidden"), (list, tuple)) and list(human["hidden"]) == default:
        human = {k: v for k, v in human.items() if k != "hidden"}
    if isinstance(human.get("clone"), dict):  # a PPO human's BC clone (mode bc_kl)
        human = {**human, "clone": _without_conv_widths(human["clone"])}
    return human


def validate(raw: dict, source: str = "") -> Spec:
    if "human" in raw:
        raw = {**raw, "human": _without_conv_widths(raw["human"])}
    human = raw.get("human")
    if isinstance(human, dict) and not isinstance(human.get("preset", ""), (str, type(None))):
        # The spec's preset step runs before field types are checked, and looks the name up.
        raise SpecError(source, "human.preset", f"expected a preset's name ({', '.join(HUMAN_PRESETS)}), "
                                                f"got {_described(human['preset'])}")
    if isinstance(human, dict) and human.get("preset") in HUMAN_PRESETS:
        # ... and looks the layout up in it by name, so the name must be text first
        env = raw.get("env") if isinstance(raw.get("env"), dict) else {}
        for where, layout in (("human.layout", human.get("layout")), ("env.layout", env.get("layout"))):
            if not isinstance(layout, (str, type(None))):
                raise SpecError(source, where, f"expected a layout's name, got {_described(layout)}")
        # ... and so the environment's, which is named first where it is none
        kind = env.get("kind")
        if "kind" in env and not (isinstance(kind, str) and kind in KIND_MODELS["env"]):
            raise SpecError(source, "env", _not_a_kind(str(kind), KIND_MODELS["env"]))
        if kind != "overcooked" and kind is not None and not human.get("layout"):
            raise SpecError(source, "human.preset", f"{human['preset']!r} names an Overcooked layout's human: "
                                                    "it needs env.kind: overcooked (a gridworld's human is a kind, "
                                                    "such as noisy_greedy)")
    try:
        return Spec.model_validate(raw)
    except ValidationError as e:
        err, msg = first_problem(e)
        loc = tuple(err["loc"])
        if err["type"] == "extra_forbidden":
            head, _, rest = str(loc[-1]).partition(".")
            if rest and head and yamlio.reads_as_name(loc[-1]):  # `train.epochs: 5` written in a file, as --set writes it
                msg += (f": a dotted key path is for --set and budgets; in a file, nest it: "
                        f"`{head}: {{{rest}: ...}}`")
            else:
                msg += did_you_mean(loc[-1], _valid_names(loc))
        section = KIND_MODELS.get(str(loc[0]) if loc else "", {})
        if err["type"] == "union_tag_not_found":
            msg = f"needs a `kind`: one of {', '.join(section)}"
            given = err.get("input") if isinstance(err.get("input"), dict) else {}
            typo = difflib.get_close_matches("kind", [str(k) for k in given], n=1, cutoff=0.6)
            if loc == ("human",) and "preset" in given:  # the section is its preset alone, and it names none known
                loc, msg = loc + ("preset",), (f"{_described(given['preset'])} is not a preset; known: "
                                               f"{', '.join(HUMAN_PRESETS)}" + did_you_mean(str(given["preset"])[:100], HUMAN_PRESETS))
            elif typo:
                loc, msg = loc + (typo[0],), f"unknown key; did you mean `kind`? (the section {msg})"
        elif err["type"] == "union_tag_invalid":
            msg = _not_a_kind(err.get("ctx", {}).get("tag"), section)
        raise SpecError(source, _spec_path(loc, err["type"] == "extra_forbidden"), msg + other_problems(e, _spec_path)) from None


def _merge(base: dict, child: dict) -> dict:
    """`child` over `base`, section by section. A child section naming a different `kind`
    replaces the base section (its fields belong to another model); otherwise keys merge."""
    out = copy.deepcopy(base)
    for key, value in child.items():
        old = out.get(key)
        if isinstance(old, dict) and isinstance(value, dict) and not _replaces(old, value):
            out[key] = _merge(old, value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_raw(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict:
    """The YAML tree of a spec file. `extends: other.yaml` (relative to this file) starts from
    that spec and applies this file's keys over it (see `_merge`)."""
    raw = _read_extended(path) if _seen else _read_yaml(path)
    if "extends" not in raw:
        return raw
    parent = raw.pop("extends")
    if not isinstance(parent, str) or not parent:
        raise SpecError(str(path), "extends", "must be the path of another spec file")
    if len(_seen) + 1 >= MAX_EXTENDS:
        raise SpecError(str(_seen[0]), "extends", f"a chain of more than {MAX_EXTENDS} files extending one another "
                        f"(file {MAX_EXTENDS} of it is {path}); shorten it")
    named = Path(path).parent / parent
    if yamlio.leads_nowhere(named):
        raise SpecError(str(path), "extends", f"{parent[:60]!r}: {yamlio.DANGLING_LINK}")
    try:
        base_path = named.resolve()
        here = Path(path).resolve()
    except (OSError, RuntimeError, ValueError) as e:  # a symlink loop, a NUL in the name
        raise SpecError(str(path), "extends", f"cannot follow {parent[:60]!r}: {e}") from None
    if base_path in _seen or base_path == here:
        raise SpecError(str(path), "extends", f"circular: {parent} extends this file again")
    if not base_path.exists():
        raise SpecError(str(path), "extends", f"file not found: {parent}")
    if not base_path.is_file():
        raise SpecError(str(path), "extends", f"{parent} is not a file")
    return _merge(_budgets_for(load_raw(base_path, _seen + (here,)), raw), raw)


def _replaces(old: Any, new: Any) -> bool:
    """A child section naming another kind than its base's replaces it (`_merge`)."""
    return isinstance(old, dict) and isinstance(new, dict) and new.get("kind", old.get("kind")) != old.get("kind")


def _budgets_for(base: dict, child: dict) -> dict:
    """`base` without its budget entries for the sections that `child` replaces by another kind:
    they were written for the base's kind (as a budget's entries do not apply to a section whose
    kind --set changed). The child's own budgets may set the new kind's fields."""
    replaced = [key for key, value in child.items() if _replaces(base.get(key), value)]
    budgets = base.get("budgets")
    if not replaced or not isinstance(budgets, dict):
        return base
    kept = {name: {k: v for k, v in entries.items() if not any(_within(str(k), r) for r in replaced)}
            if isinstance(entries, dict) else entries for name, entries in budgets.items()}
    return {**base, "budgets": kept}


MAX_EXTENDS = 32  # files in one `extends:` chain: far above any real layering
SPEC_FILE_KEYS = set(Spec.model_fields) | {"extends"}  # `budget` too: refused later, with its own message


def _read_extended(path: Path) -> dict:
    """A file that `extends:` names, read only if it is a spec: its top level a mapping of spec
    sections. It may be any file the user can read (a spec from elsewhere could name
    ~/.aws/credentials), so where it is not, the error names it and at most a line number,
    never its content, which would reach a terminal or a job's log."""
    try:
        raw = yamlio.read(path)
    except yamlio.YamlInputError as e:
        line = re.search(r"\bline ([0-9]+)", str(e))
        raise SpecError(str(path), "", "not a spec file esr can read" + (f" (line {line[1]})" if line else "")
                        + "; `extends:` must name a spec file") from None
    if not isinstance(raw, dict) or not set(raw) <= SPEC_FILE_KEYS:
        raise SpecError(str(path), "", "not a spec file (its top level is not a mapping of spec sections); "
                        "`extends:` must name a spec file")
    return raw


def _read_yaml(path: str | Path) -> dict:
    source = str(path)
    try:
        raw = yamlio.read(path)  # bounded: size limit, no aliases, no duplicate keys
    except yamlio.YamlInputError as e:
        raise SpecError(source, "", str(e)) from None
    if not isinstance(raw, dict):
        raise SpecError(source, "", "the top level must be a mapping of sections")
    return raw


def resolve(raw: dict, budget: str = "paper", overrides: list[str] | tuple[str, ...] = (), source: str = "") -> Spec:
    """Apply budget then overrides to a raw spec tree and validate it. A value that fails names
    where it came from: the `--set` that gave it, or the budget that set it."""
    if budget not in BUDGETS:
        raise SpecError(source, "--budget", f"unknown budget {budget!r}; known: {', '.join(BUDGETS)}")
    if "budget" in raw:
        raise SpecError(source, "budget", "a run's budget is chosen with --budget, not in the spec file "
                        "(the file's `budgets:` section says what each budget changes)")
    # The file as written must be valid on its own: a budget must not hide a bad value.
    validate({**copy.deepcopy(raw), "budget": "paper"}, source)
    budgets = raw.get("budgets") or {}
    if not isinstance(budgets, dict):
        raise SpecError(source, "budgets", "must be a mapping of budget name to overrides")
    if "paper" in budgets:  # else the file as written, validated and shown as the paper run, would not be it
        raise SpecError(source, "budgets.paper", "the paper budget is the spec as written: write these values in its "
                        "sections (budgets: holds quick and smoke)")
    for name in budgets:  # nor may a budget of the file other than the one chosen
        if name != budget:
            tree = copy.deepcopy(raw)
            given = _apply_budget(tree, name, budgets[name], True, set(), source)
            _validated(tree, name, given, source)
    tree = copy.deepcopy(raw)
    parsed = [(text, *parse_override(text)) for text in overrides]
    given: dict[str, str] = {}  # key path -> what set it, to name in an error
    switched = set()
    for text, dotted, value in parsed:
        if dotted.split(".")[0] in ("budget", "budgets"):
            raise SpecError("--set", dotted, "choose a budget with --budget")
        if _switch_kind(tree, dotted, value):  # before the budget, whose fields depend on the kind
            section = dotted.split(".")[0]
            switched.add(section)
            given[section] = f"--set {shown_override(text)}"  # the new kind's missing or bad fields are this --set's
    own = budget in budgets
    given.update(_apply_budget(tree, budget, budgets[budget] if own else DEFAULT_BUDGETS[budget], own, switched, source))
    for text, dotted, value in parsed:
        _set_path(tree, dotted, value, "--set")
        for field in (dotted, *_fields_set(dotted, value)):  # a mapping's fields too (the preset check reads them)
            given.pop(field, None)
            given[field] = f"--set {shown_override(text)}"
    return _validated(tree, budget, given, source)


def _apply_budget(tree: dict, budget: str, entries: Any, own: bool, switched: set[str], source: str) -> dict[str, str]:
    """Set a budget's entries in `tree`; -> {key path: what set it}."""
    where = f"budgets.{budget}" if own else f"the {budget} budget"
    if not isinstance(entries, dict):
        raise SpecError(source, f"budgets.{budget}", "must be a mapping of key.path to value")
    if twice := set_twice((str(k), str(k), v) for k, v in entries.items()):
        raise SpecError(source, f"budgets.{budget}", twice)
    given = {}
    for dotted, value in entries.items():
        dotted = str(dotted)
        if dotted.split(".")[0] in ("budget", "budgets", "name"):
            raise SpecError(f"{source}, {where}", dotted, "a budget sets fields of the run's sections, not this")
        # The default budgets name fields of every kind (e.g. ESR's update count); they apply
        # only where the spec's kind has that field. A spec's own budgets apply as written,
        # except to a section whose kind --set changed (they were written for the file's kind).
        as_written = own and dotted.split(".")[0] not in switched
        if dotted in switched:
            continue  # a whole section the budget would give: --set chose the section itself
        switches = as_written and _switch_kind(tree, dotted, value)  # as --set SECTION.kind does
        if switches:
            given[dotted.split(".")[0]] = where
        if switches or as_written or _kind_has_field(tree, dotted):
            _set_path(tree, dotted, value, f"{source}, {where}" if source else where)
            given |= dict.fromkeys((dotted, *_fields_set(dotted, value)), where)
    return given


def _preset_sets(tree: dict, dotted: str) -> str | None:
    """Where the human's preset sets the field at `dotted` (human.FIELD) to another value than the
    tree holds, what it sets it to; None otherwise. A preset replaces the fields it sets (a spec
    file's own values give way to it), so a value given for one of them would do nothing."""
    human, env = tree.get("human"), tree.get("env")
    section, _, field = dotted.partition(".")
    if section != "human" or not field or "." in field or not isinstance(human, dict):
        return None
    settings = HUMAN_PRESETS.get(human.get("preset")) if isinstance(human.get("preset"), str) else None
    layout = human.get("layout") or (env.get("layout") if isinstance(env, dict) else None)
    chosen = settings.get(layout) if settings and isinstance(layout, str) else None
    if not chosen or field not in chosen or _as_json(human.get(field)) == _as_json(chosen[field]):
        return None
    return f"the preset {human['preset']!r} sets it to {chosen[field]!r} on {layout}"


def _as_json(value: Any) -> str:
    """A value as JSON text: a list given and a tuple a preset holds compare equal."""
    return json.dumps(value, sort_keys=True, default=str)


def _validated(tree: dict, budget: str, given: dict[str, str], source: str) -> Spec:
    tree["budget"] = budget
    for dotted, origin in given.items():  # a --set or budget entry the preset would silently undo
        if preset := _preset_sets(tree, dotted):
            raise SpecError(origin if origin.startswith("--set") else f"{source}, {origin}" if source else origin, dotted,
                            f"{preset}, which replaces this value: drop it, or give the human's fields without the preset")
    try:
        spec = validate(tree, source)
        refused = _refused(spec)  # written input only: a stored spec is validated as it is
        if refused:
            raise SpecError(source, *refused)
        return spec
    except SpecError as e:
        raise _blame(e, given) from None


# Problems of one kind of a section that its builder would meet only once begun, asked when the
# spec is read: (section, kind) -> problem(the section's spec) -> (key path, problem) or None.
KIND_PROBLEMS = {("human", "ppo"): ppo_batch.problem}


def _refused(spec: Spec) -> tuple[str, str] | None:
    """(key path, problem) of what a valid spec asks that esr would refuse or ignore: a field
    where it cannot act, a PPO human whose batch PPO cannot split."""
    for (section, kind), problem_of in KIND_PROBLEMS.items():
        part = getattr(spec, section)
        problem = problem_of(part) if getattr(part, "kind", None) == kind else None
        if problem:
            return problem
    seeds = list(spec.train.seeds)
    if seeds != sorted(seeds):  # the order is part of the key, and changes no seed's numbers
        return ("train.seeds", f"{_listed(seeds)} is not in increasing order: write {_listed(sorted(seeds))} (the "
                "same seeds in another order would train a second run with the same numbers)")
    return inert_fields.first_inert(spec)


def _listed(numbers: list[int], most: int = 6) -> str:
    shown = ", ".join(map(str, numbers[:most])) + (f", ... ({len(numbers):,} seeds)" if len(numbers) > most else "")
    return f"[{shown}]"


def _switch_kind(tree: dict, dotted: str, value: Any) -> bool:
    """`--set method.kind=random` (or `method={kind: random, ...}`) on an ESR spec: the section
    starts again from the new kind, as a child file's section naming another kind replaces its
    parent's (`_merge`); ESR's fields would be unknown keys of the new model."""
    section, _, field = dotted.partition(".")
    if section not in KIND_MODELS or not isinstance(tree.get(section), dict):
        return False
    if section == "human" and not field and isinstance(value, dict) and "kind" not in value and "preset" in value:
        tree[section] = {}  # `human={preset: NAME}`: the named human, whatever the file's kind (`_human_preset`)
        return True
    kind = value if field == "kind" else value.get("kind") if not field and isinstance(value, dict) else None
    if kind is None or kind == tree[section].get("kind"):
        return False
    tree[section] = {"kind": kind}
    return True


def _within(path: str, section: str) -> bool:
    """`path` is `section` or a key or item inside it."""
    return path == section or path.startswith((section + ".", section + "["))


def _blame(e: SpecError, given: dict[str, str]) -> SpecError:
    """The error with the value's origin named: a field set by `--set` or by the budget is the
    user's mistake there, not in the file that the other fields come from; a cross-field problem
    that quotes such a field says where its value came from."""
    for dotted, origin in reversed(given.items()):  # the last --set of a path is the one that holds
        if e.path and (_within(e.path, dotted) or _within(dotted, e.path)):
            if origin.startswith("--set"):
                return SpecError(origin, e.path, e.problem)
            return SpecError(f"{e.source}, {origin}" if origin.startswith("budgets.") else e.source, e.path,
                             e.problem + ("" if origin.startswith("budgets.") else f" (set by {origin})"))
    notes = [f"{dotted} from {origin}" for dotted, origin in given.items()
             if re.search(rf"(?<![\w.]){re.escape(dotted)}(?![\w])", e.problem)]
    if notes:
        return SpecError(e.source, e.path, f"{e.problem} ({'; '.join(notes)})")
    return e


def _chain(path: str | Path) -> list[tuple[Path, dict]]:
    """The files of an `extends:` chain with their own keys, the given file first."""
    out, p = [], Path(path)
    while len(out) < MAX_EXTENDS:
        raw = _read_yaml(p)
        out.append((p, raw))
        parent = raw.get("extends")
        if not isinstance(parent, str) or not parent:
            break
        p = (p.parent / parent).resolve()
        if any(p == q.resolve() for q, _ in out):
            break
    return out


def _defines(tree: dict, dotted: str) -> bool:
    node: Any = tree
    parts = dotted.replace("[", ".[").split(".")
    for i, part in enumerate(parts):
        if part.startswith("["):
            break  # a list is written in one file as a whole
        if isinstance(node, dict) and ".".join(parts[i:]) in node:
            return True  # the path written as one dotted key (itself a mistake to name)
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


# The paper's specs and suites as installed with esr: the checkout's experiments/ (through a
# link), or the copy a wheel carries.
INSTALLED_EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def experiment_file(path: str | Path) -> Path:
    """A spec or suite file named on the command line: the path from the current directory; a
    relative `experiments/...` path that is not there is read from INSTALLED_EXPERIMENTS, so
    the README's commands work wherever an installed esr runs."""
    p = Path(path)
    if p.is_absolute() or len(p.parts) < 2 or p.parts[0] != "experiments" or p.exists():
        return p
    installed = INSTALLED_EXPERIMENTS.joinpath(*p.parts[1:])
    return installed if installed.is_file() else p


def load(path: str | Path, budget: str = "paper", overrides: list[str] | tuple[str, ...] = ()) -> Spec:
    path = experiment_file(path)
    raw = load_raw(path)
    try:
        return resolve(raw, budget, overrides, source=str(path))
    except SpecError as e:
        raise attributed(path, e) from None


def attributed(path: Path, e: SpecError) -> SpecError:
    """`e`, raised resolving the spec file `path`, naming the file that wrote the bad value (or
    budget entry) where that is a file `path` extends; `e` itself otherwise."""
    own_source = re.fullmatch(re.escape(str(path)) + r"(?:, budgets\.([\w-]+))?", e.source)
    if not own_source or not e.path:
        return e
    entry_of = own_source.group(1)  # the budget whose entry it is, or None: a value of the spec

    def writes(own: dict) -> bool:
        if entry_of is None:
            return _defines(own, e.path)
        entries = (own.get("budgets") or {}).get(entry_of)
        return isinstance(entries, dict) and e.path in map(str, entries)

    for file, own in _chain(path):
        if writes(own):
            if file != Path(path):
                where = f"{file} (extended by {path})" + (f", budgets.{entry_of}" if entry_of else "")
                return SpecError(where, e.path, e.problem)
            break
    return e


def plays_with_paper_human(spec: Spec) -> bool:
    """False for an Overcooked run on a layout the paper reports whose human is not the paper's
    (`human.preset: paper`) in any field that shapes it; its seed (one human or one per seed) aside."""
    paper = HUMAN_PRESETS["paper"].get(getattr(spec.env, "layout", None))
    if spec.env.kind != "overcooked" or paper is None:
        return True
    if spec.human.kind != paper["kind"]:
        return False
    ignored = {"preset", "seed", "per_seed", "layout"}
    made = KIND_MODELS["human"][paper["kind"]].model_validate(paper)
    return spec.human.model_dump(exclude=ignored) == made.model_dump(exclude=ignored)


def to_yaml(spec: Spec) -> str:
    return yaml.safe_dump(spec.model_dump(mode="json"), sort_keys=False)
