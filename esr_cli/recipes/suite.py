"""Suites: YAML files that name many training runs at once (docs/cluster.md).

A suite is a list of spec files, a grid of `--set` values, or both:

    name: gridworld                  # optional; default: the file's stem
    specs:                           # paths relative to this file, or entries with their own grid
      - ../grid_2.yaml
      - {spec: ../grid_5.yaml, set: {learner.gamma: 0.0}, grid: {method.repr_dim: [8, 32]}}
    set:  {train.seeds: 20}          # fixed overrides for every entry
    grid: {learner.lr: [1.0e-3, 3.0e-4]}   # cartesian product for every entry
    slurm: {partition: gpu, time_min: 720, gpus: 1, mem_gb: 32, cpus: 8}

Each run is the equivalent of `esr train SPEC --budget B --set k=v ...`: the suite-wide `set`,
then the entry's `set`, then one point of the product of the suite's and the entry's grids
(an entry's grid key replaces the suite's grid for that key). A top-level list is short for
`{specs: [...]}`. Every run is loaded and validated before any work, and every problem is a
`SuiteError` (a `SpecError`, so the CLI exits 2) naming the file, the key and the problem.
A suite expands to at most `MAX_RUNS` runs; the count is checked before any run is built.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from esr_cli.common import specs, yamlio
from esr_cli.common.printing import train_line
from esr_cli.model import spec as spec_model
from esr_cli.storage.store import content_key


class SuiteError(specs.SpecError):
    """A suite that cannot be used; `str()` is one line naming file, key path and problem."""


# Each run is loaded, validated and keyed before any work, and each is one job: far above any
# real suite (the paper's has 24 runs), low enough that expanding one takes seconds, not hours.
MAX_RUNS = 10_000


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# A spec's field names, dotted: the key is written into `--set KEY=VALUE` text, so nothing but
# names and dots may be in it (an '=' or a '#' there would set another field than it names).
_KEY_PATH = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def _check_key_paths(v: dict) -> dict:
    for dotted in v:
        if not isinstance(dotted, str) or not _KEY_PATH.fullmatch(dotted):
            raise ValueError(f"{dotted!r} is not a key path like train.seeds")
    return v


def _check_grid(v: dict) -> dict:
    _check_key_paths(v)
    for dotted, values in v.items():
        # A scalar would silently become a one-point grid; demand the list the user meant.
        if not isinstance(values, list) or not values:
            raise ValueError(f"{dotted}: a grid needs a non-empty list of values (got {values!r})")
    return v


SBATCH_WORD = re.compile(r"[^\x00-\x20\x7f]+")
SBATCH_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,63}")
CONTROL = re.compile(r"[\x00-\x1f\x7f]")


class SlurmOptions(_Model):
    """Resources of each SLURM job (one run per job, submitted as one job array). The upper
    bounds are far above any node; they catch a slip of the keyboard before sbatch does."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # The spec's number types: `gpus: true` or `gpus: "2"` is a mistake to name, not a 1 or a 2.
    partition: Optional[str] = Field(None, min_length=1)
    account: Optional[str] = Field(None, min_length=1)
    qos: Optional[str] = Field(None, min_length=1)
    time_min: spec_model.Int = Field(720, ge=1, le=366 * 24 * 60, description="wall-clock limit of one job, minutes")
    gpus: spec_model.Int = Field(1, ge=0, le=64, description="GPUs per job")
    cpus: spec_model.Int = Field(8, ge=1, le=4096, description="CPU cores per job")
    mem_gb: spec_model.Float = Field(32, gt=0, le=65_536, description="memory per job, GB")
    array_parallelism: spec_model.Int = Field(64, ge=1, le=MAX_RUNS, description="at most this many jobs of the array run at once")
    setup: tuple[str, ...] = Field((), description="shell lines run before each job (module load, ...)")
    additional: dict[str, Any] = Field(default_factory=dict, description="extra sbatch options, e.g. {constraint: a100}")

    # Each value becomes a `#SBATCH --name=value` line of the job script: a line break in one would
    # end the comment and leave the rest of the value a shell line of every job (and sbatch stops
    # reading options at the first such line, dropping the time limit and signal after it).
    @field_validator("partition", "account", "qos")
    @classmethod
    def _one_word(cls, v):
        if v is not None and not SBATCH_WORD.fullmatch(v):
            raise ValueError("must be one word of printable characters (no spaces, line breaks or control characters)")
        return v

    @field_validator("additional")
    @classmethod
    def _sbatch_lines(cls, v):
        for name, value in v.items():
            if not SBATCH_NAME.fullmatch(name):
                raise ValueError(f"{name[:40]!r} is not an sbatch option name (letters, digits, '-' and '_')")
            if isinstance(value, bool) or not isinstance(value, (str, int, float)):
                raise ValueError(f"{name}: must be a text or a number")
            if isinstance(value, str) and CONTROL.search(value):
                raise ValueError(f"{name}: must not hold a line break or a control character")
        return v


class _Overrides(_Model):
    """`set` (fixed overrides) and `grid` (overrides to cross), at a suite's top or on one entry."""

    set: dict[str, Any] = Field(default_factory=dict)
    grid: dict[str, list[Any]] = Field(default_factory=dict)

    @field_validator("set")
    @classmethod
    def _set_keys(cls, v):
        return _check_key_paths(v)

    @field_validator("grid", mode="before")
    @classmethod
    def _grid_lists(cls, v):
        return _check_grid(v) if isinstance(v, dict) else v

    @model_validator(mode="after")
    def _each_field_once(self):
        # Within one mapping the order of its keys would decide; the grid's points apply after
        # `set`, so a field in both would take the grid's values whatever `set` says.
        fixed = [(f"{k} (in set)", k, v) for k, v in self.set.items()]
        crossed = [(f"{k} (in grid)", k, v) for k, values in self.grid.items() for v in values]
        if twice := specs.set_twice(fixed) or specs.set_twice(crossed) or specs.replaced_later(fixed, crossed):
            raise ValueError(twice)
        return self


class EntryModel(_Overrides):
    spec: str = Field(..., min_length=1)

    @field_validator("spec")
    @classmethod
    def _a_path(cls, v):
        if "\0" in v:  # no file system names such a file
            raise ValueError("a spec file's path cannot hold a NUL character")
        return v


class SuiteModel(_Overrides):
    name: Optional[str] = Field(None, min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.\-]+$")
    specs: tuple[EntryModel, ...] = Field(..., min_length=1)
    slurm: SlurmOptions = SlurmOptions()

    @field_validator("specs", mode="before")
    @classmethod
    def _paths_are_entries(cls, v):
        if isinstance(v, list):
            return [{"spec": e} if isinstance(e, str) else e for e in v]
        return v


@dataclass(frozen=True)
class Run:
    """One training run of a suite: the equivalent of `esr train spec_path --budget B --set ...`."""

    spec_path: Path  # absolute
    sets: tuple[str, ...]  # `--set` texts, in the order they apply
    spec: spec_model.Spec  # validated, budget and sets applied
    key: str  # the training run's content key (runs.run_key)

    @property
    def label(self) -> str:
        return " ".join((self.spec.name, *self.sets))

    def command(self, budget: str, esr: str = "esr") -> str:
        """The `esr train` line of this run; `esr`: how to call esr (Store.invocation)."""
        return train_line(esr, self.spec_path, budget, self.sets)


@dataclass(frozen=True)
class Suite:
    path: Path
    name: str
    budget: str
    runs: tuple[Run, ...]
    slurm: SlurmOptions
    duplicates: int  # entries that named a run another entry already names

    @property
    def key(self) -> str:
        """Names the suite's sweep state file: the suite's name, budget and runs as written
        (spec files and overrides, not the run keys, so a code change keeps its job records)."""
        return content_key({
            "name": self.name,
            "budget": self.budget,
            "runs": [[r.spec_path.name, list(r.sets)] for r in self.runs],
        })


def _set_text(dotted: str, value: Any) -> str:
    # JSON is YAML, and `--set` parses its value as YAML: the text round-trips exactly.
    return f"{dotted}={json.dumps(value, separators=(',', ':'))}"


def _validate(raw: Any, source: str) -> SuiteModel:
    if isinstance(raw, list):
        raw = {"specs": raw}
    if not isinstance(raw, dict):
        raise SuiteError(source, "", "a suite is a mapping with a `specs:` list, or a list of spec files")
    entries = raw.get("specs")
    if isinstance(entries, list) and len(entries) > MAX_RUNS:  # before each entry is validated
        raise SuiteError(source, "specs", f"{len(entries):,} entries, more than the {MAX_RUNS:,} runs a suite may "
                                          "hold: split it into several suites")
    if "specs" not in raw and {"env", "method"} & set(raw):
        raise SuiteError(source, "", "this is a spec file, not a suite (a suite lists spec files under `specs:`): "
                                     "train it with `esr train`, or name it in a suite's `specs:` list")
    try:
        return SuiteModel.model_validate(raw)
    except ValidationError as e:
        err, msg = specs.first_problem(e)
        loc = tuple(err["loc"])
        if err["type"] == "extra_forbidden":
            msg += specs.did_you_mean(loc[-1], _suite_names(loc))
        raise SuiteError(source, yamlio.key_path(loc), msg + specs.other_problems(e)) from None


def _suite_names(loc: tuple) -> list[str]:
    """The keys valid where an unknown key `loc[-1]` was found in a suite."""
    if len(loc) == 1:
        return list(SuiteModel.model_fields)
    if loc[0] == "slurm" and len(loc) == 2:
        return list(SlurmOptions.model_fields)
    if loc[0] == "specs" and len(loc) == 3:
        return list(EntryModel.model_fields)
    return []


def run_count(model: SuiteModel) -> int:
    """The runs a suite names before duplicates are dropped: per entry, the product of its grid
    sizes (the suite's grid with the entry's keys replaced), summed over entries. Counted, not built."""
    return sum(math.prod(len(v) for v in {**model.grid, **entry.grid}.values()) for entry in model.specs)


def _origin(e: specs.SpecError, spec_path: Path) -> str:
    """': WHERE: PATH: PROBLEM' of a spec's error, after the suite entry that names the spec: where
    in the spec's files the value came from (a file it extends, a budget's entry), unless that is
    the spec file itself or the entry's own --set values, which the entry already names."""
    where = e.source
    if where == str(spec_path) or where.startswith("--set"):
        where = ""
    elif where.startswith(f"{spec_path}, "):
        where = where[len(f"{spec_path}, "):]  # its own budget's entry: 'budgets.smoke'
    inner = f"{e.path}: {e.problem}" if e.path else e.problem
    return f": {where}: {inner}" if where else f": {inner}"


def load(path: str | Path, budget: str = "paper") -> Suite:
    """Read, validate and expand a suite: every run's spec is loaded and validated here."""
    p = specs.experiment_file(path)
    source = str(p)
    if budget not in spec_model.BUDGETS:
        raise SuiteError(source, "--budget", f"unknown budget {budget!r}; known: {', '.join(spec_model.BUDGETS)}")
    try:
        raw = yamlio.read(p)  # bounded: size limit, no aliases, no duplicate keys
    except yamlio.YamlInputError as e:
        raise SuiteError(source, "", str(e)) from None
    model = _validate(raw, source)
    count = run_count(model)
    if count > MAX_RUNS:
        raise SuiteError(source, "", f"expands to {count:,} runs, more than the {MAX_RUNS:,} a suite may hold: "
                                     "shrink its grids or split it into several suites")

    from esr_cli.recipes import runs  # the run key needs jax (toolchain); import only when expanding

    base = p.resolve().parent
    out: list[Run] = []
    seen: set[str] = set()
    duplicates = 0
    # Each spec file (and its chain of `extends`) is read once, however many entries name it:
    # resolving copies the tree, never changes it.
    read: dict[Path, dict] = {}
    for i, entry in enumerate(model.specs):
        where = f"specs[{i}]"
        named = base / entry.spec
        if yamlio.leads_nowhere(named):  # checked before resolving it, which a loop would make raise
            raise SuiteError(source, f"{where}.spec", f"{entry.spec}: {yamlio.DANGLING_LINK}")
        if not named.exists() and not Path(entry.spec).is_absolute():
            raise SuiteError(source, f"{where}.spec", f"{entry.spec}: file not found (a suite's spec paths are read "
                                                      f"from the suite file's folder, {base})")
        spec_path = named.resolve()
        try:
            if spec_path not in read:
                read[spec_path] = specs.load_raw(spec_path)
        except specs.SpecError as e:
            raise SuiteError(source, f"{where}.spec", f"{entry.spec}{_origin(e, spec_path)}") from None
        raw_spec = read[spec_path]
        if "specs" in raw_spec and "env" not in raw_spec:
            raise SuiteError(source, f"{where}.spec", f"{entry.spec} is a suite, not a spec file: suites do not nest "
                             "(list its spec files here)")
        grid = {**model.grid, **entry.grid}
        # The suite's grid applies after the entry's own `set`: a field in both would take the
        # suite's values whatever the entry says.
        over = [(f"{k} (in the suite's grid)", k, v) for k, values in model.grid.items() if k not in entry.grid for v in values]
        if twice := specs.replaced_later([(f"{k} (in this entry's set)", k, v) for k, v in entry.set.items()], over):
            raise SuiteError(source, where, twice)
        fixed = [_set_text(k, v) for k, v in {**model.set, **entry.set}.items()]
        names = list(grid)
        for point in itertools.product(*(grid[k] for k in names)):
            sets = tuple(fixed + [_set_text(k, v) for k, v in zip(names, point)])
            try:
                spec = specs.resolve(raw_spec, budget, list(sets), source=str(spec_path))
            except specs.SpecError as e:
                # Name the suite entry and the overrides too: the spec file alone may be fine.
                at = f" with {' '.join(specs.shown_override(t) for t in sets)}" if sets else ""
                raise SuiteError(source, where, f"{entry.spec}{at}{_origin(specs.attributed(spec_path, e), spec_path)}") from None
            key, _ = runs.run_key(spec)
            if key in seen:
                duplicates += 1
                continue
            seen.add(key)
            out.append(Run(spec_path, sets, spec, key))
    return Suite(p, model.name or p.stem, budget, tuple(out), model.slurm, duplicates)
