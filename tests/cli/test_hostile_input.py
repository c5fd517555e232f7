"""Hostile and careless input: bounded work before validation, errors that name the real
mistake, resources checked before anything is compiled or written (docs/reliability.md)."""

import copy
import json
import os
import stat
import re
import time
import tracemalloc
from pathlib import Path

import pytest
import yaml
from conftest import ROOT, esr
from hypothesis import HealthCheck, given, settings, strategies as st

from esr_cli.cli.main import main
from esr_cli.common import specs, yamlio
from esr_cli.model import spec as spec_model
from esr_cli.recipes import suite as suites
from esr_cli.runner import resources

VALID = """name: t
env: {kind: gridworld, blocks: 2}
human: {kind: noisy_greedy}
method: {kind: esr}
"""


def cpu_seconds() -> float:
    """This process's CPU time: an in-process bound on the work a refusal does, which other
    processes on a loaded machine (the suite's own workers, a training run) cannot stretch."""
    return time.process_time()


def child_cpu_seconds() -> float:
    """CPU time of this process's finished children (the CLI subprocesses): a bound on a
    refusal's work that a loaded machine cannot stretch, as wall time would be."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def write(tmp_path, text, name="s.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def alias_bomb() -> str:
    """Nine levels of nine-fold aliases in about 600 bytes: 9^9 strings if expanded."""
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 10):
        lines.append(f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    return VALID + "\n".join(lines) + "\n"


def test_alias_bomb_is_refused_at_once_in_little_memory(tmp_path):
    p = write(tmp_path, alias_bomb())
    tracemalloc.start()
    t0 = cpu_seconds()
    with pytest.raises(specs.SpecError, match=r"line 5: anchors \(&name\) are not allowed"):
        specs.load(p)
    elapsed = cpu_seconds() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert elapsed < 5.0 and peak < 200 * 2**20  # a blow-up takes minutes; a loaded machine, seconds


def test_alias_bomb_through_the_cli_writes_nothing(tmp_path):
    p = write(tmp_path, alias_bomb())
    proc = esr("train", str(p), store=tmp_path / "store", check=False)
    assert proc.returncode == 2 and "anchors" in proc.stderr
    assert not (tmp_path / "store" / "runs").exists()


def test_plain_alias_and_duplicate_keys_name_their_lines(tmp_path):
    with pytest.raises(yamlio.YamlInputError, match=r"line 2: aliases \(\*name\)"):
        yamlio.parse("a: 1\nb: *x\n")
    dup = VALID + "train: {epochs: 5}\ntrain: {epochs: 7}\n"
    with pytest.raises(specs.SpecError, match=r"key 'train' appears twice in one mapping \(lines 5 and 6\)"):
        specs.load(write(tmp_path, dup))
    with pytest.raises(specs.SpecError, match="key 'kind' appears twice"):
        specs.load(write(tmp_path, VALID.replace("{kind: esr}", "{kind: esr, kind: ave}")))


def test_an_error_location_reads_as_the_key_path_written():
    """Indices in brackets, tags left out, an unknown last key shown even when it is a number,
    and a key that is not a name only by its length."""
    assert yamlio.key_path(("questionnaire", 1, "likert", "scale")) == "questionnaire[1].likert.scale"
    assert yamlio.key_path(("questionnaire", 1, "likert", "scale"), lambda i, part: part == "likert") == "questionnaire[1].scale"
    assert yamlio.key_path(("a", 3), last_is_key=True) == "a.3"
    assert yamlio.key_path(("a", "x y\x1b[2J")) == "a.(a key of 7 characters that is not a name)"
    assert yamlio.key_path(()) == ""


def test_oversized_file_is_refused_unread(tmp_path):
    p = write(tmp_path, VALID + "# " + "x" * (yamlio.MAX_FILE_BYTES + 10) + "\n")
    with pytest.raises(specs.SpecError, match="larger than the 262,144 bytes"):
        specs.load(p)


def test_a_file_whose_size_is_not_reported_is_read_only_to_the_limit(tmp_path, monkeypatch):
    """/proc files report a size of 0: the read itself stops one byte past the limit."""
    p = write(tmp_path, VALID + "# " + "x" * (yamlio.MAX_FILE_BYTES + 10) + "\n")
    real_stat = Path.stat

    def unsized(self, *args, **kwargs):
        st = real_stat(self, *args, **kwargs)
        return os.stat_result((st.st_mode, st.st_ino, st.st_dev, st.st_nlink, st.st_uid, st.st_gid, 0,
                               int(st.st_atime), int(st.st_mtime), int(st.st_ctime))) if self == p else st

    monkeypatch.setattr(Path, "stat", unsized)
    assert p.stat().st_size == 0
    with pytest.raises(specs.SpecError, match="more than the 262,144"):
        specs.load(p)


def test_a_typo_is_named_first_with_the_closest_name(tmp_path):
    with pytest.raises(specs.SpecError) as e:
        specs.load(write(tmp_path, VALID.replace("method:", "methd:")))
    assert str(e.value).startswith(f"{tmp_path / 's.yaml'}: methd: unknown key; did you mean `method`?")
    with pytest.raises(specs.SpecError, match=r"method.repr_dimm: unknown key; did you mean `repr_dim`\?"):
        specs.load(write(tmp_path, VALID.replace("{kind: esr}", "{kind: esr, repr_dimm: 3}")))
    with pytest.raises(specs.SpecError, match=r"learner.bach_size: unknown key; did you mean `batch_size`\?"):
        specs.load(write(tmp_path, VALID + "learner: {bach_size: 3}\n"))


@pytest.mark.parametrize("field,value", [("learner.lr", ".inf"), ("human.noise", ".nan"), ("method.repr_lr", "-.inf"),
                                         ("learner.gamma", ".nan")])
def test_non_finite_numbers_are_refused_by_name(tmp_path, field, value):
    with pytest.raises(specs.SpecError, match=f"{field}: Input should be a finite number"):
        specs.load(write(tmp_path, VALID), "paper", [f"{field}={value}"])


def test_huge_seed_count_is_refused_before_it_is_built(tmp_path):
    t0 = cpu_seconds()
    with pytest.raises(specs.SpecError, match="train.seeds: 1,000,000,000 seeds: at most 1,024"):
        specs.load(write(tmp_path, VALID), "paper", ["train.seeds=1000000000"])
    assert cpu_seconds() - t0 < 5.0
    with pytest.raises(specs.SpecError, match=r"^[^\n]{0,200}train.seeds: \(a number of 400 digits\) seeds: at most 1,024"):
        specs.load(write(tmp_path, VALID), "paper", ["train.seeds=" + "9" * 400])
    with pytest.raises(specs.SpecError, match="environment steps"):
        specs.load(write(tmp_path, VALID), "paper", ["train.epochs=10000000", "train.num_envs=100000"])


def test_memory_estimate_by_hand():
    spec = specs.load(ROOT / "experiments/grid_2.yaml", "paper", ["train.seeds=3"])
    # 15,000 // 50 = 300 episodes of 51 observations of 5x5x2 bytes, and 12 bytes per step
    est = resources.estimate(spec, resources.observation_bytes(spec), seeds_at_once=1)
    assert resources.observation_bytes(spec) == 50
    assert est.buffers == 3 * 300 * (51 * 50 + 12 * 50)
    assert est.rollouts == 1 * 100 * 51 * (5 * 50 + 64)
    assert est.total == 2 * (est.buffers + est.rollouts) + resources.RUNTIME_BYTES


def test_the_memory_estimate_names_aves_rollouts_as_the_part_to_lower():
    """AvE's simulated rollouts are its update's memory, not the networks': a refusal says so."""
    spec = specs.load(ROOT / "experiments/grid_2_ave.yaml", "paper",
                      ["train.seeds=1", "method.num_rollouts=10000", "method.rollout_length=10000"])
    shape, obs_bytes, actions = resources.observation(spec)
    est = resources.estimate(spec, obs_bytes, 1, shape, actions)
    assert est.updates == 2 * spec.learner.batch_size * 10_000 * 10_001 * 50  # batch x rollouts x (length + 1) x 2 observations
    assert est.updates > 1000 * est.networks
    assert est.field_to_lower == "learner.batch_size, or method.num_rollouts or method.rollout_length"
    assert f"the method's updates {est.updates / resources.GIB:,.2f} GiB" in est.parts()
    assert est.total == 2 * (est.buffers + est.rollouts + est.networks + est.updates) + resources.RUNTIME_BYTES
    # ESR's updates (the batch x batch InfoNCE logits) grow with the batch alone: no AvE field is named
    esr = specs.load(ROOT / "experiments/grid_2.yaml", "paper",
                     ["train.seeds=1", "learner.batch_size=1000000", "learner.buffer_size=2000000"])
    shape, obs_bytes, actions = resources.observation(esr)
    est = resources.estimate(esr, obs_bytes, 1, shape, actions)
    assert est.updates == 16 * 1_000_000 ** 2 and est.field_to_lower == "learner.batch_size"


@pytest.mark.slow
def test_huge_buffer_is_refused_before_anything_is_compiled_or_written(tmp_path):
    t0 = child_cpu_seconds()
    proc = esr("train", "experiments/grid_5.yaml", "--set", "learner.buffer_size=100000000000",
               store=tmp_path / "store", check=False)
    assert proc.returncode == 2
    assert "too large for this machine" in proc.stderr and "lower learner.buffer_size" in proc.stderr
    assert not (tmp_path / "store" / "runs").exists()
    assert child_cpu_seconds() - t0 < 60


def test_global_options_after_the_command(tmp_path):
    from esr_cli.cli.main import global_options_first

    assert global_options_first(["exact", "s.yaml", "--store", "D", "--debug"]) == ["--store", "D", "--debug", "exact", "s.yaml"]
    assert global_options_first(["ls", "--store=D"]) == ["--store=D", "ls"]
    assert global_options_first(["train", "s.yaml", "--", "--store"]) == ["train", "s.yaml", "--", "--store"]
    proc = esr("exact", "experiments/grid_2.yaml", "--goal", "9,9", "--store", str(tmp_path / "elsewhere"),
               store=tmp_path / "store", check=False)
    assert proc.returncode == 2 and "outside the 5x5 grid" in proc.stderr and "No such option" not in proc.stderr


def test_suite_files_follow_the_same_rules(tmp_path):
    bad = tmp_path / "suite.yaml"
    bad.write_text("name: x\nspecs: &s [a.yaml]\nset: *s\n")
    with pytest.raises(suites.SuiteError, match="anchors"):
        suites.load(bad)
    bad.write_text("name: x\nspecs: [a.yaml]\nname: y\n")
    with pytest.raises(suites.SuiteError, match="key 'name' appears twice"):
        suites.load(bad)
    with pytest.raises(specs.SpecError, match="--set: learner: value is not valid YAML: line 1: anchors"):
        specs.load(ROOT / "experiments/grid_2.yaml", "paper", ["learner=&a {lr: 1}"])


# ---------------------------------------------------------------- fuzz
BASES = [specs.load_raw(ROOT / "experiments" / name) for name in
         ("grid_2.yaml", "grid_5_ave.yaml", "grid_7_iq_learn.yaml", "cramped_room.yaml", "coord_ring_random.yaml")]
ODD_VALUES = [None, "x", -1, 0, 10**12, 1e300, -1e-300, [], {}, True, float("inf"), float("nan"), [1] * 50, "1e-4",
              {"kind": "esr"}, "a" * 5000]


def _paths(tree, prefix=()):
    for k, v in tree.items():
        yield prefix + (k,)
        if isinstance(v, dict):
            yield from _paths(v, prefix + (k,))


@st.composite
def hostile_texts(draw):
    tree = copy.deepcopy(draw(st.sampled_from(BASES)))
    paths = list(_paths(tree))
    op = draw(st.sampled_from(["drop", "retype", "inflate", "duplicate", "alias", "rename"]))
    path = draw(st.sampled_from(paths))
    parent = tree
    for k in path[:-1]:
        parent = parent[k]
    if op == "drop":
        parent.pop(path[-1])
    elif op == "retype":
        parent[path[-1]] = draw(st.sampled_from(ODD_VALUES))
    elif op == "inflate":
        parent[path[-1]] = {"k": [list(range(50))] * draw(st.integers(1, 200))}
    elif op == "rename":
        parent[path[-1] + draw(st.sampled_from(["s", "_", "x"]))] = parent.pop(path[-1])
    text = yaml.safe_dump(tree, sort_keys=False)
    lines = text.splitlines()
    i = draw(st.integers(0, len(lines) - 1))
    if op == "duplicate":
        lines.insert(i, lines[i])
    elif op == "alias":
        lines[i] = lines[i] + " &z" if lines[i].rstrip().endswith(":") else lines[i]
        lines.append("zz: *z")
    return "\n".join(lines) + "\n"


FUZZ_CASES = 400


@pytest.mark.slow
@settings(max_examples=FUZZ_CASES, deadline=2000, suppress_health_check=[HealthCheck.too_slow,
                                                                         HealthCheck.function_scoped_fixture])
@given(text=hostile_texts())
def test_fuzzed_specs_are_a_clean_spec_or_a_one_line_error(tmp_path, text):
    """Every mutation of a valid spec (a key dropped, renamed, duplicated, retyped, inflated or
    aliased) loads as a valid spec or raises SpecError with a one-line message, fast."""
    p = tmp_path / "fuzz.yaml"
    p.write_text(text)
    t0 = cpu_seconds()
    for budget in ("paper", "smoke"):
        try:
            specs.load(p, budget)
        except specs.SpecError as e:
            assert "\n" not in str(e) and str(e).startswith(str(p))
    assert cpu_seconds() - t0 < 10.0


def test_published_ave_on_overcooked_validates():
    spec = specs.load(ROOT / "experiments/cramped_room_ave.yaml", "smoke", ["method.variant=original"])
    assert spec.method.variant == "original"  # tests/model/test_baselines.py checks what it computes


# ---------------------------------------------------------------- types, bounds, blame
@pytest.mark.parametrize("override, message", [
    ("train.epochs=true", r"train.epochs: expected an integer, got the boolean true"),
    ('train.seeds=["3"]', r"train.seeds\[0\]: expected an integer, got the text '3'"),
    ("method.repr_lr=false", r"method.repr_lr: expected a number, got the boolean false"),
    ('method.repr_lr="1e-3"', r"method.repr_lr: expected a number, got the text '1e-3' \(write it without quotes\)"),
    ("method.repr_lr=nan", r"method.repr_lr: expected a number, got the text 'nan' \(not a finite number\)"),
    ("learner.gamma=-inf", r"learner.gamma: expected a number, got the text '-inf' \(not a finite number\)"),
    ("env.goal_visible=1", r"env.goal_visible: expected true or false"),
    ("train.seeds=[4294967296]", r"train.seeds: seeds must be between 0 and 2,147,483,647"),
    ("network.mlp_layers=[-5]", r"network.mlp_layers\[0\]: Input should be greater than or equal to 1"),
    ("network.conv_channels=[0]", r"network.conv_channels\[0\]: Input should be greater than or equal to 1"),
    ("network.hidden=1000000", r"network.hidden: Input should be less than or equal to 16384"),
    ("network.mlp_layers=[8,8,8,8,8,8,8,8,8,8,8,8,8,8,8,8,8]", r"network.mlp_layers: Value error, 17 layers: at most 16|17 layers: at most 16"),
    ("method.repr_dim=100000", r"method.repr_dim: Input should be less than or equal to 16384"),
    ("budget=quick", r"--set: budget: choose a budget with --budget"),
    ("train.epochs=null", r"train.epochs: the value is empty \(null\): write one, or leave the key out"),
    ("network.conv_channels=16", r"network.conv_channels: expected a list, e.g. \[a, b\], got the number 16"),
    ("train.epochs=1e20", r"train.epochs: the number is far too large for this setting"),
    ("learner.lr=1" + "0" * 400, r"learner.lr: the number is far too large for this setting"),
    ("learner.lr=._", r"learner.lr: expected a number, got the text '._'$"),
    ("env.kind=overcooked", r"^--set env.kind=overcooked: env.layout: missing: this key is required"),
])
def test_a_value_of_the_wrong_type_or_size_is_named(tmp_path, override, message):
    with pytest.raises(specs.SpecError, match=message):
        specs.load(write(tmp_path, VALID), "paper", [override])


def test_whole_floats_still_count_as_integers(tmp_path):
    spec = specs.load(write(tmp_path, VALID), "paper", ["learner.buffer_size=2e4", "train.epochs=1e3"])
    assert spec.learner.buffer_size == 20_000 and spec.train.epochs == 1000
    with pytest.raises(specs.SpecError, match="train.epochs: Input should be a valid integer, got a number with a fractional part"):
        specs.load(write(tmp_path, VALID), "paper", ["train.epochs=5.5"])


def test_text_that_looks_like_a_number_stays_text(tmp_path):
    assert specs.load(write(tmp_path, VALID.replace("name: t", 'name: "1.5"'))).name == "1.5"


def test_a_kind_that_is_not_a_name_is_refused_under_every_budget(tmp_path):
    """A budget's defaults are applied where the kind has the field; a kind given as a list or a
    mapping names no kind, and is refused as one, not looked up."""
    for budget in ("paper", "quick", "smoke"):
        for value in ("[esr]", "{a: 1}"):
            with pytest.raises(specs.SpecError, match=r"method: kind .* is not one of esr, random"):
                specs.load(write(tmp_path, VALID), budget, [f"method.kind={value}"])
            # an env kind too, beside a human preset (which looks the env's kind up)
            with pytest.raises(specs.SpecError, match=r"env: kind .* is not one of gridworld, overcooked"):
                specs.load("experiments/cramped_room.yaml", budget, [f"env.kind={value}"])


def test_unknown_top_level_keys_are_named_even_when_they_spell_a_kind(tmp_path):
    for key in ("random", "esr", "gridworld"):
        with pytest.raises(specs.SpecError, match=rf"s.yaml: {key}: unknown key"):
            specs.load(write(tmp_path, VALID + f"{key}: 3\n"))


def test_missing_or_unknown_kind_lists_the_kinds(tmp_path):
    with pytest.raises(specs.SpecError, match=r"env: needs a `kind`: one of gridworld, overcooked$"):
        specs.load(write(tmp_path, VALID.replace("{kind: gridworld, blocks: 2}", "{}")))
    with pytest.raises(specs.SpecError, match=r"method: kind 'esrr' is not one of esr, random, ave"):
        specs.load(write(tmp_path, VALID.replace("{kind: esr}", "{kind: esrr}")))
    with pytest.raises(specs.SpecError, match=r"env: expected a section \(a mapping of keys\), got the text 'gridworld'"):
        specs.load(write(tmp_path, VALID.replace("{kind: gridworld, blocks: 2}", "gridworld")))


def test_a_budget_in_the_file_is_refused(tmp_path):
    with pytest.raises(specs.SpecError, match=r"s.yaml: budget: a run's budget is chosen with --budget"):
        specs.load(write(tmp_path, VALID + "budget: quick\n"), "quick")


def test_a_bad_value_from_an_extended_file_names_that_file(tmp_path):
    write(tmp_path, VALID.replace("{kind: esr}", "{kind: esr, repr_dim: -1}"), "a.yaml")
    write(tmp_path, "extends: a.yaml\nname: b\n", "b.yaml")
    c = write(tmp_path, "extends: b.yaml\ntrain: {epochs: 3}\n", "c.yaml")
    with pytest.raises(specs.SpecError) as e:
        specs.load(c)
    assert str(e.value).startswith(f"{tmp_path / 'a.yaml'} (extended by {c}): method.repr_dim:")
    d = write(tmp_path, "extends: b.yaml\nmethod: {repr_dim: 0}\n", "d.yaml")
    with pytest.raises(specs.SpecError, match=rf"^{d}: method.repr_dim:"):
        specs.load(d)


@pytest.mark.parametrize("kind, params", [("conv", dict(conv_channels=(16, 32), hidden=100)),
                                          ("conv", dict(conv_channels=(), hidden=7)),
                                          ("mlp", dict(mlp_layers=(64, 3)))])
def test_network_size_estimate_counts_the_real_parameters(kind, params):
    """resources' parameter count is the flax network's, computed without building it."""
    import jax
    import numpy as np

    from esr_cli.model.networks import conv_net

    net_spec = spec_model.NetworkSpec(kind=kind, **params)
    obs = np.zeros((1, 5, 4, 3), np.uint8)
    shapes = jax.eval_shape(conv_net(net_spec, 32).init, jax.random.PRNGKey(0), obs)
    real = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(shapes))
    assert resources._network_floats(net_spec, (5, 4, 3), 32)[0] == real


@pytest.mark.slow
def test_networks_too_wide_for_memory_are_refused_before_any_work(tmp_path):
    t0 = child_cpu_seconds()
    proc = esr("train", "experiments/grid_5.yaml", "--set", "network.hidden=16384",
               "--set", "network.conv_channels=[16384,16384,16384]", store=tmp_path / "store", check=False)
    assert proc.returncode == 2, proc.stderr
    assert "too large for this machine" in proc.stderr and "lower the network's widths" in proc.stderr
    assert not (tmp_path / "store" / "runs").exists()
    assert child_cpu_seconds() - t0 < 60


# ---------------------------------------------------------------- suites, sweeps, eval, exact
GRID_2 = ROOT / "experiments" / "grid_2.yaml"


def _refused_fast(fn, match, seconds=3.0, mib=50):
    """fn() raises SuiteError matching `match`, in bounded time and memory."""
    tracemalloc.start()
    t0 = cpu_seconds()
    try:
        with pytest.raises(suites.SuiteError, match=match) as e:
            fn()
    finally:
        elapsed = cpu_seconds() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert "\n" not in str(e.value)
    assert elapsed < seconds and peak < mib * 2**20, (elapsed, peak)
    return e.value


@pytest.mark.slow
def test_suite_expansion_is_capped_before_anything_is_built(tmp_path):
    limit = f"{suites.MAX_RUNS:,}"
    grid = "".join(f"  learner.k{i}: [{', '.join(str(v) for v in range(10))}]\n" for i in range(6))
    p = write(tmp_path, f"specs: [{GRID_2}]\ngrid:\n{grid}", "grid.yaml")
    err = _refused_fast(lambda: suites.load(p), rf"expands to 1,000,000 runs, more than the {limit}")
    assert err.path == ""
    # An entry's grid multiplies the suite's grid; entries add up.
    p = write(tmp_path, f"specs:\n  - {GRID_2}\n  - {{spec: {GRID_2}, grid: {{learner.a: {list(range(101))}}}}}\n"
                        f"grid: {{learner.b: {list(range(100))}}}\n", "product.yaml")
    _refused_fast(lambda: suites.load(p), rf"expands to 10,200 runs, more than the {limit}")
    # A long entries list is refused before its entries are validated (reading the YAML
    # itself, bounded by the file size, is most of the time here).
    p = write(tmp_path, "specs: [" + ", ".join(["a.yaml"] * 12_000) + "]\n", "entries.yaml")
    err = _refused_fast(lambda: suites.load(p), rf"12,000 entries, more than the {limit}", seconds=10)
    assert err.path == "specs"


def test_huge_suite_through_the_cli_exits_2_and_writes_nothing(tmp_path):
    grid = "".join(f"  learner.k{i}: [{', '.join(str(v) for v in range(10))}]\n" for i in range(6))
    p = write(tmp_path, f"specs: [{GRID_2}]\ngrid:\n{grid}", "grid.yaml")
    proc = esr("sweep", str(p), "--status", store=tmp_path / "store", check=False)
    assert proc.returncode == 2 and "1,000,000 runs" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "store").exists()


@pytest.mark.slow
def test_sweep_results_refuses_an_unknown_metric(tmp_path):
    p = write(tmp_path, f"specs: [{GRID_2}]\n", "suite.yaml")
    proc = esr("sweep", str(p), "--budget", "smoke", "--results", "--metric", "return", "--metric", "bogus",
               store=tmp_path / "store", check=False)
    assert proc.returncode == 2 and "--metric: unknown metric 'bogus'" in proc.stderr, proc.stderr
    known = proc.stderr.split("known:")[1]
    assert "return" in known and "success" in known and "mi_estimate" in known
    assert not (tmp_path / "store").exists()


@pytest.mark.parametrize("slurm, problem", [("mem_gb: .inf", "slurm.mem_gb: Input should be a finite number"),
                                            ("mem_gb: .nan", "slurm.mem_gb: Input should be a finite number"),
                                            ("time_min: 100000000", "slurm.time_min: Input should be less than or equal"),
                                            ("gpus: 100000", "slurm.gpus: Input should be less than or equal"),
                                            ("gpus: true", "slurm.gpus: expected an integer, got the boolean true"),
                                            ("gpus: '2'", "slurm.gpus: expected an integer, got the text '2'"),
                                            ("partition: ''", "slurm.partition: String should have at least 1 character"),
                                            ("setup: 'module load x'", "slurm.setup: expected a list"),
                                            # a value is a `#SBATCH` line: a line break would make the rest a shell line
                                            ('partition: "gpu\\ntouch /tmp/x\\n#"', "slurm.partition: must be one word"),
                                            ('qos: "a b"', "slurm.qos: must be one word"),
                                            ('additional: {constraint: "a100\\necho x"}', "slurm.additional: constraint: must not hold a line break"),
                                            ('additional: {"x\\ny": 1}', "slurm.additional: .* is not an sbatch option name"),
                                            ("additional: {constraint: [a, b]}", "slurm.additional: constraint: must be a text or a number")])
def test_slurm_options_refuse_non_finite_and_absurd_values(tmp_path, slurm, problem):
    p = write(tmp_path, f"specs: [{GRID_2}]\nslurm: {{{slurm}}}\n", "suite.yaml")
    with pytest.raises(suites.SuiteError, match=problem) as e:
        suites.load(p)
    assert "pydantic" not in str(e.value) and "\n" not in str(e.value)


def test_slurm_overrides_on_the_command_line_are_one_line_errors(tmp_path):
    from esr_cli.recipes import sweep

    p = write(tmp_path, f"specs: [{GRID_2}]\n", "suite.yaml")
    with pytest.raises(suites.SuiteError) as e:
        sweep.run_suite(p, "smoke", "slurm", tmp_path / "store", slurm={"cpus": 0})
    assert str(e.value).endswith("--cpus: Input should be greater than or equal to 1"), str(e.value)
    assert not (tmp_path / "store").exists()
    for option, value, problem in (("--mem-gb", "inf", "--mem-gb: Input should be a finite number"),
                                   ("--cpus", "0", "--cpus: Input should be greater than or equal to 1"),
                                   ("--partition", "gpu\ntouch /tmp/x\n#", "--partition: must be one word")):
        proc = esr("sweep", str(p), "--executor", "slurm", option, value, store=tmp_path / "store", check=False)
        assert proc.returncode == 2 and problem in proc.stderr, proc.stderr
        assert "pydantic" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "store").exists()


def test_eval_episodes_are_bounded_like_the_spec(tmp_path):
    field = spec_model.EvalSpec.model_fields["episodes"]
    bound = f"{next(m.le for m in field.metadata if getattr(m, 'le', None) is not None):,}"  # the spec's own bound
    for n in ("0", "-3", "1000001", "10000000000000"):
        proc = esr("eval", str(GRID_2), "--episodes", n, store=tmp_path / "store", check=False)
        assert proc.returncode == 2 and "--episodes: between 1 and " + bound in proc.stderr, proc.stderr
        assert "not trained" not in proc.stderr and not (tmp_path / "store").exists()


@pytest.mark.slow
def test_options_that_only_apply_to_a_spec_file_are_refused_with_an_artifact(tmp_path):
    store = tmp_path / "store"
    for args, problem in (
        (["eval", "0123abcd", "--set", "train.seeds=2"], "--set applies to a spec file"),
        (["eval", "0123abcd", "--budget", "smoke"], "--budget applies to a spec file"),
        (["exact", str(GRID_2), "--seed-index", "2"], "--seed-index applies to --robot"),
        (["plot", "gridworld", "0123abcd"], "takes no artifact"),
        (["plot", "estimator", "0123abcd", "--budget", "smoke"], "--budget"),
        (["plot", "geometry", "--budget", "quick"], "--budget"),
        (["plot", "mi", "--gamma", "0.5"], "--gamma"),
        (["plot", "estimator", "0123abcd", "--state", "1"], "--state"),
        (["plot", "geometry", "--unfinished"], "--unfinished applies to the paper figures"),
        (["plot", "mi", "--out", "x"], "--out applies to `esr plot curve`, or to a paper figure with --unfinished"),
    ):
        proc = esr(*args, store=store, check=False)
        assert proc.returncode == 2 and problem in proc.stderr, (args, proc.stderr)
        assert "no artifact with key" not in proc.stderr and not store.exists()


def test_exact_on_a_huge_state_space_is_refused_before_any_work(tmp_path):
    t0 = child_cpu_seconds()
    proc = esr("exact", str(GRID_2), "--set", "env.size=16", "--set", "env.blocks=40", store=tmp_path / "store", check=False)
    assert proc.returncode == 2, proc.stderr
    assert "env.size" in proc.stderr and "env.blocks" in proc.stderr and "30,000" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "store").exists()
    assert child_cpu_seconds() - t0 < 30  # the process start and imports; no enumeration


@pytest.mark.parametrize("value", ["9x", "-5s"])
def test_a_bad_stop_after_is_a_usage_error_before_any_work(tmp_path, value):
    store = tmp_path / "store"
    proc = esr("train", "experiments/grid_2.yaml", "--budget", "smoke", "--stop-after", value, store=store, check=False)
    assert proc.returncode == 2 and "--stop-after: expected a duration such as 90s" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and not store.exists()


def test_durations_by_hand():
    from esr_cli.cli.app import Exit, parse_duration

    assert parse_duration("90", "--x") == 90.0
    assert parse_duration("90s", "--x") == 90.0
    assert parse_duration("9m", "--x") == 540.0
    assert parse_duration("1.5H", "--x") == 5400.0
    assert parse_duration("0", "--x") == 0.0
    for bad in ("", "m", "-5s", "nan", "inf", "9x", "400d", "1e9h", "5 minutes"):
        with pytest.raises(Exit, match="--x: expected a duration"):
            parse_duration(bad, "--x")


@pytest.mark.parametrize("text, value", [
    ("010", 10), ("1_000", 1000), ("-3", -3), ("1e-4", 1e-4), ("true", True), ("FALSE", False),
    ("yes", "yes"), ("on", "on"), ("off", "off"), ("1:30", "1:30"), ("0b101", "0b101"), ("0x1f", "0x1f"),
    ("0o17", "0o17"), ("True", True), ("TRUE", True), ("False", False),
    ("2020-01-01", "2020-01-01"), ("~", None), ("+.5", 0.5), ("-.5", -0.5), (".5e3", 500.0), ("._", "._"),
    ("!!float 3", 3.0), ("!!bool true", True), ("!!int \"3\"", 3), ("!!null", None), ("!!null NULL", None),
])
def test_scalars_read_as_yaml_1_2_not_1_1(text, value):
    assert yamlio.parse(f"a: {text}") == {"a": value}


@pytest.mark.parametrize("text, problem", [
    ("!!binary /w==", "the tag !!binary is not allowed"), ("!!set {x}", "the tag !!set is not allowed"),
    ("!!timestamp 2020-01-01", "the tag !!timestamp is not allowed"),
    ("9" * 5000, "an integer of 5,000 digits; at most 4,000"),
    ("!!float abc", "'abc' is not a number"), ("!!bool yes", "'yes' is not true or false"),
    ("!!null x", "'x' is not null"),
    ("{1: 2}", "the key 1 is a number, not a name"), ("{null: 2}", "the key null is null, not a name"),
    ("{~: 2}", "the key ~ is null, not a name"), ("{? : 2}", r"the key \(empty\) is null, not a name"),
    ("{True: 2}", "the key True is a boolean, not a name"), ("{[1]: 2}", "the key is a list or mapping, not a name"),
    ("{" + "1" * 70 + ": 2}", "the key \\(a key of 70 characters that is not a name\\) is a number, not a name"),
    ("{<<: {b: 1}}", r"merge keys \(<<\) are not allowed; write each value out"),
])
def test_values_that_are_not_spec_values_are_refused_by_line(text, problem):
    with pytest.raises(yamlio.YamlInputError, match=f"line 1: {problem}"):
        yamlio.parse(f"a: {text}")


@pytest.mark.parametrize("text, where, character", [
    ("name: a\x1bb\n", "line 1, column 8", "U+001B"), ("a: 1\nb: x\x00\n", "line 2, column 5", "U+0000"),
    ("a: 1\n\x7f", "line 2, column 1", "U+007F"),
    ("a: 1\r\nb: 2\rc: \x1b", "line 3, column 4", "U+001B"),  # lines as YAML counts them: CRLF, CR
])
def test_a_character_yaml_refuses_is_named_by_line_and_column_on_one_line(text, where, character):
    with pytest.raises(yamlio.YamlInputError) as e:
        yamlio.parse(text)
    assert str(e.value) == f"unreadable YAML: {where}: the character {character} is not allowed in YAML"


def test_a_tab_between_a_key_and_its_value_is_named_as_a_tab():
    with pytest.raises(yamlio.YamlInputError, match=r"line 1, column 5: .*'\\t'.* \(a tab: write spaces instead\)$"):
        yamlio.parse("env:\t{kind: gridworld}\n")


def test_yaml_1_1_booleans_and_true_as_a_seat_are_named(tmp_path):
    for override, problem in (("env.goal_visible=yes", "env.goal_visible: expected true or false"),
                              (f"train.epochs={'9' * 5000}", "an integer of 5,000 digits")):
        with pytest.raises(specs.SpecError, match=problem):
            specs.load(ROOT / "experiments/grid_2.yaml", "smoke", [override])
    with pytest.raises(specs.SpecError, match="env.robot_seat: expected 0 or 1, got the boolean true"):
        specs.load(ROOT / "experiments/cramped_room.yaml", "smoke", ["env.robot_seat=true"])
    p = write(tmp_path, f"specs: [{ROOT / 'experiments/grid_2.yaml'}]\nset: {{name: 2020-01-01}}\n", "suite.yaml")
    suites.load(p)  # a date-like name is text, not a date that JSON cannot hold


def test_a_mapping_override_sets_its_keys_and_keeps_the_sections_others():
    grid = ROOT / "experiments/grid_2.yaml"
    assert specs.load(grid, "paper", ["train={epochs: 5}"]) == specs.load(grid, "paper", ["train.epochs=5"])
    assert len(specs.load(grid, "paper", ["train={epochs: 5}"]).train.seeds) == 20  # the file's seeds stay


def test_rich_markup_in_user_text_is_printed_as_text(tmp_path, capsys):
    for argv in (["show", "zz[/b]"], ["eval", "[/x]"], ["train", str(tmp_path / "d[/x]" / "s.yaml")]):
        assert main(["--store", str(tmp_path / "store"), *argv]) == 2
        err = capsys.readouterr().err
        assert "[/" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_a_store_path_that_looks_like_markup_is_printed_as_written(tmp_path, capsys):
    """Paths printed for scripts to read are the paths: `[bold]` is not styled away, `[/x]` is
    not a crash after the work is done."""
    from esr_cli.storage.store import Store, content_key

    components = {"kind": "runs", "spec": {"name": "x"}}
    key = content_key(components)
    here = tmp_path / "s[bold]x[/x]"
    store = Store(here)
    (store.begin("runs", key, {"name": "x", "key": key, "key_components": components}) / "metrics.jsonl").write_text("")
    path = store.commit("runs", key, {"kind": "runs", "name": "x", "key": key, "key_components": components})
    assert main(["--store", str(here), "verify"]) == 0
    assert "".join(capsys.readouterr().err.split()) == f"ok{path}"  # a long line may be folded
    archive = tmp_path / "a[red]b.tar.gz"
    assert main(["--store", str(here), "export", key[:8], "--out", str(archive)]) == 0
    assert capsys.readouterr().out.strip() == str(archive)
    there = tmp_path / "t[/]"
    assert main(["--store", str(there), "import", str(archive)]) == 0
    assert capsys.readouterr().out.strip() == str(there / "runs" / key[:2] / key)
    assert main(["--store", str(there), "show", key[:8], "--json"]) == 0
    shown = capsys.readouterr()
    assert shown.err.strip() == str(there / "runs" / key[:2] / key) and json.loads(shown.out)["key"] == key


def test_only_the_printing_module_makes_consoles():
    """Every console reads no markup (esr_cli/common/printing.py), so user text is safe at any print site;
    a console made elsewhere would read `[/x]` in a path as a closing tag again."""
    import ast

    package = ROOT / "esr_cli"
    makers = set()
    for f in package.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Call) and str(getattr(node.func, "id", getattr(node.func, "attr", None))).endswith("Console"):
                makers.add(f.relative_to(package).as_posix())
    assert makers == {"common/printing.py"}


def test_an_empty_store_path_is_refused_rather_than_read_as_the_current_directory(capsys):
    for empty in ("", "  "):
        assert main(["--store", empty, "ls"]) == 2
        assert "--store: an empty path" in capsys.readouterr().err


def test_a_file_name_too_long_is_a_usage_error(tmp_path, capsys):
    assert main(["--store", str(tmp_path / "store"), "train", str(tmp_path / ("a" * 300 + ".yaml"))]) == 2
    assert "file name too long" in capsys.readouterr().err
    assert main(["--store", str(tmp_path / ("b" * 300)), "ls"]) == 2
    assert "file name too long" in capsys.readouterr().err


def test_eval_and_report_options_are_checked_before_the_store(tmp_path, capsys):
    store = ["--store", str(tmp_path / "store")]
    for argv, problem in ((["eval", "experiments/cramped_room.yaml", "--seat", "5"], "--seat: 0 or 1, got 5"),
                          (["eval", "experiments/cramped_room.yaml", "-b", "smoke", "--human", "play:zz"], "'zz' is not a play artifact's key"),
                          (["eval", "experiments/cramped_room.yaml", "-b", "smoke", "--human", "play:ABCD\x1b[2J"], "'abcd\\x1b[2j' is not a play artifact's key"),
                          (["eval", "experiments/grid_2.yaml", "--human", "play:zz"], "--human play is a BC human (Overcooked)"),
                          (["eval", "experiments/cramped_room.yaml", "--human", "play:zz"], "this run's human is 'ppo'"),
                          (["eval", "experiments/grid_2.yaml", "--seat", "1"], "a gridworld has one robot seat"),
                          (["paper", "--report", "--out", str(tmp_path)], "is a directory; name a file"),
                          (["paper", "--report", "--out", str(ROOT / "README.md" / "x.md")], "README.md is a file"),
                          (["play", "experiments/grid_2.yaml", "--seed", "99999999999999999999"], "--seed: between 0 and")):
        assert main([*store, *argv]) == 2, argv
        err = capsys.readouterr().err
        assert problem in err and "not trained" not in err, err
    assert not (tmp_path / "store").exists() and not list(tmp_path.glob(".*tmp*"))


@pytest.mark.parametrize("flags, problem", [
    (["--status", "--results"], "choose one"), (["--status", "--metric", "x"], "--metric applies with --results only"),
    (["--plot"], "--plot applies with --results only"), (["--results", "--json", "--markdown"], "choose one"),
    (["--results", "--unfinished"], "--unfinished applies with --results --plot only"),
    (["--results", "--out", "x"], "--out applies with --results --plot only --unfinished"),
    (["--results", "--plot", "--out", "x"], "--out is the folder of a preview of unfinished runs: only with --plot --unfinished"),
    (["--partition", "p"], "--partition: not used by --executor local"),
    (["--executor", "submitit-local", "--gpus", "1"], "--gpus: not used by --executor submitit-local"),
    (["--executor", "slurm", "--time-min", "5", "--status"], "--status and --results submit nothing"),
    (["--no-wait"], "--wait/--no-wait: for submitted jobs"),
])
def test_sweep_options_that_would_be_ignored_are_refused(tmp_path, capsys, flags, problem):
    assert main(["--store", str(tmp_path / "store"), "sweep", "experiments/suites/gridworld.yaml", *flags]) == 2
    assert problem in capsys.readouterr().err
    assert not (tmp_path / "store").exists()


@pytest.mark.slow
def test_usage_errors_and_help_are_answered_without_loading_jax(tmp_path):
    """Refusing bad input costs the interpreter's start, not JAX's and orbax's import (seconds):
    the checks come before the heavy modules are imported."""
    for args in (["--help"], ["train", str(tmp_path / "missing.yaml")], ["train", "experiments/grid_2.yaml", "--set", "nope=1"],
                 ["train", "experiments/grid_2.yaml", "--stop-after", "9x"], ["plot", "mi", "--gamma", "0.5"],
                 ["exact", "experiments/grid_2.yaml", "--goal", "x"], ["exact", "experiments/grid_2.yaml", "--seed-index", "1"],
                 ["eval", "experiments/grid_2.yaml", "--human", "nope"], ["eval", "experiments/grid_2.yaml", "--seat", "1"],
                 ["eval", "deadbeef"], ["diagnose", "deadbeef"], ["ablate"],
                 ["ablate", "experiments/grid_2.yaml", "--greedy", "--set", "nope=1"], ["paper", "--executor", "nope"],
                 ["plot", "estimator", "deadbeef"], ["paper", "--json"], ["paper", "--report", "--budget", "smoke"],
                 ["plot", "geometry", "--gamma", "1.5"], ["plot", "gridworld", "--budget", "bogus"],
                 ["exact", "experiments/cramped_room.yaml"], ["exact", "experiments/grid_5.yaml"],
                 ["exact", "experiments/grid_4x4_3.yaml", "--goal", "9,9"],
                 ["ablate", "experiments/grid_5_random.yaml", "--greedy"]):
        _assert_refused_without_jax(args, tmp_path / "store", 0 if args == ["--help"] else 2)


@pytest.mark.parametrize("args, problem", [
    (["paper", "--json"], "--json: applies to `esr paper --report` only; add --report"),
    (["paper", "--no-exact", "--out", "r.md"], "--exact/--no-exact, --out: apply to `esr paper --report` only"),
    (["paper", "--report", "--executor", "slurm"], "--executor: applies to training the paper suite"),
    (["paper", "--budget", "huge"], "--budget: unknown budget 'huge'"),
    (["plot", "geometry", "--state", "7"], "--state must be 0, 1 or 2, got 7"),
    (["plot", "curve", "deadbeef", "--out", "c.txt"], "--out: c.txt: a figure is written as .jpeg, .jpg, .pdf, .png, .svg"),
    (["exact", "experiments/grid_4x4_3.yaml", "--gamma", "1.0"], "--gamma must be in [0, 1), got 1.0"),
    (["exact", "experiments/cramped_room.yaml"], "exact empowerment is defined for gridworld specs only"),
    (["ablate", "experiments/grid_5_ave.yaml", "--no-robot-action"], "--no-robot-action ablates ESR's representations"),
    (["ablate", "experiments/grid_5_random.yaml", "--greedy"], "Goal Inference robots learn none); this spec's method is 'random'"),
    (["ablate", "experiments/grid_5_goal_inference.yaml", "--greedy"], "--greedy ablates a method that learns a critic"),
    (["ablate", "experiments/grid_5.yaml", "--set", "learner.gamma=0.9"], "it changes nothing to compare"),
    (["ablate", "experiments/grid_5.yaml", "experiments/grid_5.yaml", "--greedy"], "name each base spec once"),
    (["ablate", "experiments/grid_5.yaml", "--greedy", "--set", "learner.gamma=0"], "are the same training run"),
    (["ablate", "experiments/grid_2.yaml", "--greedy", "--set", "learner.buffer_size=50000000000"],
     "too large for this machine: grid_2 needs about"),
    (["ablate", "--greedy", "--budget", "bogus"], "--budget: unknown budget 'bogus'"),
    (["eval", "ffff", "--set", "x=1"], "ffff is not a spec file but a run's key or path"),
    (["export", "ffff", "--out", "run.zip"], "--out: run.zip would hold a gzipped tar archive: name it with .tar.gz"),
    (["export", "ffff", "--out", "/proc/run.tar.gz"], "--out: cannot write in /proc"),
])
def test_options_that_the_command_would_ignore_or_cannot_use_are_named(tmp_path, capsys, args, problem):
    """Each refusal names the option at fault, before any work: a forgotten --report must not
    start the paper suite's training, an ablation that changes nothing must not train twice."""
    assert main(["--store", str(tmp_path / "store"), *args]) == 2
    assert problem in capsys.readouterr().err
    assert not (tmp_path / "store").exists()


def test_ablate_finds_its_default_specs_from_any_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["--store", str(tmp_path / "store"), "ablate", "--greedy", "--budget", "bogus"]) == 2
    from esr_cli.report import paper

    assert all(Path(p).is_file() for p in paper.DEFAULT_ABLATION_SPECS)


def test_a_file_where_a_store_folder_belongs_is_named(tmp_path, capsys):
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "runs").write_text("")
    for args in (["train", "experiments/grid_2.yaml", "--budget", "smoke"], ["ls"]):
        assert main(["--store", str(tmp_path / "store"), *args]) == 2
        assert "runs is a file where its runs folder belongs" in capsys.readouterr().err


@pytest.mark.slow
def test_options_that_do_not_fit_a_stored_run_are_refused_without_loading_jax(smoke_run):
    """`eval` and `diagnose` on a trained run check their options against its spec and record
    (two small files) before the training code is imported."""
    store, path, _ = smoke_run
    for args in (["eval", path.name, "--seat", "1"], ["eval", path.name, "--human", "proxy"],
                 ["diagnose", path.name, "--seed-index", "7"], ["diagnose", path.name[:8], "--refit", "5", "--episodes", "1"],
                 ["plot", "estimator", path.name]):
        _assert_refused_without_jax(args, store, 2)


def _assert_refused_without_jax(args, store, code):
    import subprocess
    import sys

    probe = ("import sys; from esr_cli.cli.main import main; code = main(sys.argv[1:]); "
             "print(code, 'jax' in sys.modules, 'orbax.checkpoint' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", probe, "--store", str(store), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.stdout.split()[-3:] == [str(code), "False", "False"], (args, proc.stdout, proc.stderr)


def test_a_dotted_key_in_a_file_is_named_as_one(tmp_path):
    with pytest.raises(specs.SpecError, match=r"train.epochs: unknown key: a dotted key path is for --set and budgets; "
                       r"in a file, nest it: `train: \{epochs: ...\}`"):
        specs.load(write(tmp_path, VALID + "train.epochs: 5\n"))


def test_every_budget_of_the_file_is_checked_whichever_is_chosen(tmp_path):
    """A typo in the quick budget is named when the paper budget runs; a budget entry that
    changes a kind restarts that section, as --set does, and its problems are the budget's."""
    path = write(tmp_path, VALID + "budgets: {quick: {train.epoch: 5}}\n")
    with pytest.raises(specs.SpecError, match=r"budgets.quick: train.epoch: unknown key; did you mean `epochs`"):
        specs.load(path, "paper")
    for entries, problem in (("{budgets.smoke: {}}", "budgets.smoke: a budget sets fields of the run's sections"),
                             ("{a..b: 1}", "a..b: malformed key path"),
                             ("{env.kind: overcooked}", "env.layout: missing: this key is required")):
        with pytest.raises(specs.SpecError, match=re.escape(f"budgets.quick: {problem}")):
            specs.load(write(tmp_path, VALID + f"budgets: {{quick: {entries}}}\n"), "quick")
    switched = specs.load(write(tmp_path, VALID + "budgets: {quick: {method.kind: random}}\n"), "quick")
    assert switched.method.kind == "random"


def test_extends_that_cannot_be_followed_are_named(tmp_path):
    (tmp_path / "l1.yaml").symlink_to(tmp_path / "l2.yaml")
    (tmp_path / "l2.yaml").symlink_to(tmp_path / "l1.yaml")
    (tmp_path / "loop.yaml").write_text("extends: l1.yaml\n")
    (tmp_path / "nul.yaml").write_text('extends: "a\\0b.yaml"\n')
    for name, problem in (("loop", "extends: 'l1.yaml': a symbolic link that leads to no file"), ("nul", "extends: cannot follow")):
        with pytest.raises(specs.SpecError, match=problem):
            specs.load(tmp_path / f"{name}.yaml")
    write(tmp_path, VALID, "d0.yaml")
    for i in range(1, specs.MAX_EXTENDS + 1):
        (tmp_path / f"d{i}.yaml").write_text(f"extends: d{i - 1}.yaml\n")
    assert specs.load(tmp_path / f"d{specs.MAX_EXTENDS - 1}.yaml").name == "t"
    with pytest.raises(specs.SpecError, match=f"d{specs.MAX_EXTENDS}.yaml: extends: a chain of more than"):
        specs.load(tmp_path / f"d{specs.MAX_EXTENDS}.yaml")


def test_small_slips_get_messages_that_point_at_them(tmp_path, capsys):
    """A spec path without .yaml where a run is expected, an empty key path, a key twice on one
    line, a folder given as an archive."""
    cases = ((["eval", "experiments/grid_2"], "(the spec file is experiments/grid_2.yaml)"),
             (["train", "experiments/grid_2.yaml", "--set", "=1"], "--set: =1: no key path before '='"),
             (["train", str(write(tmp_path, "a: {b: 1, b: 2}\n"))], "key 'b' appears twice in one mapping (line 1)"),
             (["import", str(tmp_path / "x.tar.gz")], "x.tar.gz: a directory, not an archive"))
    (tmp_path / "x.tar.gz").mkdir()
    for args, problem in cases:
        assert main(["--store", str(tmp_path / "store"), *args]) == 2
        assert problem in capsys.readouterr().err


@pytest.mark.slow  # trains the shared smoke run
def test_a_reference_that_names_no_finished_artifact_says_what_is_wrong(smoke_run, tmp_path, capsys):
    store, path, _ = smoke_run
    unfinished = tmp_path / "s" / "runs" / path.parent.name / f"{path.name}.partial"
    unfinished.mkdir(parents=True)
    (unfinished / "pending.json").write_text(json.dumps({"kind": "runs", "key": path.name, "name": "grid_2"}))
    cases = (([store, "show", ""], "an empty key"), ([store, "verify", ""], "an empty key"),
             ([store, "show", path.name + "dead"], "has 36 hex digits: a key has 32"),
             ([store, "show", str(path / "spec.yaml")], "is a file inside the artifact"),
             ([tmp_path / "s", "verify", str(unfinished)], "is unfinished (no manifest yet)"),
             ([tmp_path / "none", "verify"], "no store at"))
    for (where, *args), problem in cases:
        assert main(["--store", str(where), *args]) == 2, args
        assert problem in capsys.readouterr().err, args
    assert main(["--store", str(store), "show", path.name[:8].upper()]) == 0  # keys in either case
    capsys.readouterr()
    # show describes an unfinished run from its pending.json; verify checks finished artifacts only
    assert main(["--store", str(tmp_path / "s"), "show", path.name[:8]]) == 0
    assert "status:        partial" in capsys.readouterr().out


def test_a_store_where_nothing_can_be_written_is_named_before_any_work(capsys):
    assert main(["--store", "/proc/esr", "train", "experiments/grid_2.yaml", "--budget", "smoke"]) == 2
    assert "store /proc/esr is not writable" in capsys.readouterr().err


def test_a_compile_cache_that_is_not_a_folder_is_named_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("ESR_COMPILE_CACHE", str(write(tmp_path, "x", "a_file")))
    assert main(["--store", str(tmp_path / "s"), "train", "experiments/grid_2.yaml", "--budget", "smoke"]) == 2
    assert "ESR_COMPILE_CACHE=" in capsys.readouterr().err and not (tmp_path / "s").exists()


# ---------------------------------------------------------------- text from a store reaches no terminal raw
HOSTILE = "a\x1b[2J\u202e\nb"  # clears the screen; turns the rest of the line around; starts a line


def _hostile_store(root: Path) -> tuple[str, str]:
    """A store holding a run and a played episode whose name, participant, manifest fields and
    a file name hold HOSTILE; -> (run key, played key)."""
    from esr_cli.storage.play_log import EPISODE_FILE
    from esr_cli.storage.store import Store, content_key

    store = Store(root)
    keys = []
    for kind, extra in (("runs", {"seeds": [0], "budget": HOSTILE}), ("play", {"summary": {"completed": True, "steps": 3, "score": 1.0}})):
        components = {"kind": kind, "spec": {"name": HOSTILE}}
        key = content_key(components)
        d = store.begin(kind, key, {"name": HOSTILE, "key": key, "key_components": components})
        if kind == "play":
            (d / EPISODE_FILE).write_text(json.dumps({"participant": HOSTILE, "session": HOSTILE, "episode": 0,
                                                      "robot": HOSTILE, "env": {"kind": HOSTILE}, "started_at": 0}))
        path = store.commit(kind, key, {"kind": kind, "name": HOSTILE, "key": key, "key_components": components, **extra})
        keys.append(key)
    (path.parent.parent.parent / "runs" / keys[0][:2] / keys[0] / f"extra{HOSTILE}").write_text("")  # verify names it
    return keys[0], keys[1]


@pytest.mark.slow
def test_control_characters_from_a_store_are_printed_as_escapes(tmp_path):
    """ls (a run's name and budget), show (its manifest and path), plays (participant, session,
    robot, env) and verify (a file name in a problem) print what the store holds, escaped."""
    run, _ = _hostile_store(tmp_path / "store")
    for args in (["ls"], ["show", run[:8]], ["plays"], ["verify"]):
        proc = esr(*args, store=tmp_path / "store", check=False, COLUMNS="300")
        printed = proc.stdout + proc.stderr
        assert "\x1b" not in printed and "\u202e" not in printed, args
        assert "a\\x1b[2J\\u202e\\nb" in printed or "a\\u001b[2J\\u202e\\nb" in printed, (args, printed)
        assert "\\u202e\n" not in printed, (args, printed)  # the newline after it is an escape too
    assert esr("verify", store=tmp_path / "store", check=False).returncode == 1  # the extra file


@pytest.mark.slow
def test_a_file_name_holding_a_newline_cannot_forge_a_line_of_verify(tmp_path, capsys):
    """A newline read from a store is an escape, so a file named `x\\nok FORGED-LINE` in an
    artifact cannot print an `ok` line of its own; esr's own message of several lines (the
    commands a figure needs) still prints line by line."""
    from esr_cli.storage.store import Store, content_key

    components = {"kind": "runs", "spec": {"name": "x"}}
    key = content_key(components)
    store = Store(tmp_path / "store")
    store.begin("runs", key, {"name": "x", "key": key, "key_components": components})
    path = store.commit("runs", key, {"kind": "runs", "name": "x", "key": key, "key_components": components})
    (path / "x\nok FORGED-LINE").write_text("")
    assert main(["--store", str(tmp_path / "store"), "verify"]) == 1
    err = capsys.readouterr().err
    assert "unexpected file x\\nok FORGED-LINE" in err
    assert not any(line.strip().startswith("ok FORGED-LINE") for line in err.splitlines()), err
    assert main(["--store", str(tmp_path / "empty"), "plot", "greedy", "--budget", "smoke"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert "needs 12 run(s) the store lacks; make them with:" in lines[0] and lines[1].startswith("  esr ")
    # the store named, as every hint names it
    assert lines[-1] == f"or all at once: esr --store {tmp_path / 'empty'} paper --budget smoke", lines


def test_a_dangling_or_looping_link_as_a_spec_is_named_as_a_link(tmp_path):
    a, b, dangling = tmp_path / "a.yaml", tmp_path / "b.yaml", tmp_path / "dangling.yaml"
    a.symlink_to(b)
    b.symlink_to(a)
    dangling.symlink_to(tmp_path / "gone.yaml")
    for link in (a, dangling):
        with pytest.raises(yamlio.YamlInputError, match="a symbolic link that leads to no file"):
            yamlio.read(link)
    with pytest.raises(yamlio.YamlInputError, match="^file not found$"):
        yamlio.read(tmp_path / "gone.yaml")
    # named the same as a suite's entry and as a file a spec extends (a loop never raised uncaught)
    for link in (a, dangling):
        (tmp_path / "suite.yaml").write_text(f"specs: [{link.name}]\n")
        with pytest.raises(suites.SuiteError, match=f"specs\\[0\\].spec: {link.name}: a symbolic link that leads to no file"):
            suites.load(tmp_path / "suite.yaml", "smoke")
        (tmp_path / "child.yaml").write_text(f"name: c\nextends: {link.name}\n")
        with pytest.raises(specs.SpecError, match=f"extends: '{link.name}': a symbolic link that leads to no file"):
            specs.load(tmp_path / "child.yaml")


def test_a_fifo_given_as_a_spec_is_refused_without_waiting(tmp_path, monkeypatch):
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    proc = esr("train", str(fifo), store=tmp_path / "store", check=False, timeout=60)
    assert proc.returncode == 2 and "pipe.yaml: not a file" in proc.stderr
    # A FIFO put in a checked file's place is refused when opened, not waited on.
    import signal

    monkeypatch.setattr(Path, "is_file", lambda self: True)
    signal.alarm(20)  # a regression would block here; the alarm ends the test instead
    try:
        with pytest.raises(yamlio.YamlInputError, match="not a regular file"):
            yamlio.read(fifo)
    finally:
        signal.alarm(0)


@pytest.mark.parametrize("content", [
    "[default]\naws_secret_access_key = SECRET\n",  # INI: not YAML
    "aws_secret_access_key: SECRET\n",  # YAML, but no spec
    '{"auths": {"registry": {"auth": "SECRET"}}}\n',  # JSON is YAML
    "- SECRET\n",
    "SECRET: 1\nSECRET: 2\n",  # yamlio's own refusals quote what they refuse (a key given twice)
    "SECRET",
])
def test_extending_a_file_that_is_not_a_spec_never_quotes_it(tmp_path, content):
    """A spec from elsewhere may `extends:` any file the user can read; its content must not
    reach the terminal or a job's log through the error."""
    (tmp_path / "credentials").write_text(content)
    child = write(tmp_path, "extends: credentials\nname: t\n")
    with pytest.raises(specs.SpecError) as caught:
        specs.load(child)
    assert "SECRET" not in str(caught.value) and "credentials" in str(caught.value)
    assert "not a spec file" in str(caught.value)


def test_the_memory_check_respects_cgroup_and_address_space_limits(tmp_path, monkeypatch):
    """A container's or a job's cgroup limit (v2 or v1), and `ulimit -v`, can be far below the
    machine's free memory: the least of them is what a run may take."""
    import resource

    gib = 1 << 30
    for folder, limit, used in (("", "max", 0), ("job", str(3 * gib), gib), ("memory", str(8 * gib), 0),
                                ("memory/job", str(gib + 5), 5)):
        d = tmp_path / folder
        d.mkdir(parents=True, exist_ok=True)
        v1 = folder.startswith("memory")
        (d / ("memory.limit_in_bytes" if v1 else "memory.max")).write_text(limit + "\n")
        (d / ("memory.usage_in_bytes" if v1 else "memory.current")).write_text(f"{used}\n")
    cgroups = tmp_path / "proc_self_cgroup"
    monkeypatch.setattr(resources, "CGROUP_ROOT", tmp_path)
    monkeypatch.setattr(resources, "PROC_CGROUP", cgroups)
    cgroups.write_text("0::/job\n")
    assert resources.cgroup_bytes() == 2 * gib
    cgroups.write_text("4:cpu,memory:/job\n0::/\n")
    assert resources.cgroup_bytes() == gib
    cgroups.write_text("0::/\n")
    assert resources.cgroup_bytes() is None  # "max": no limit
    real = resource.getrlimit
    monkeypatch.setattr(resource, "getrlimit", lambda r: (64 * gib, resource.RLIM_INFINITY) if r == resource.RLIMIT_AS else real(r))
    assert 0 < resources.address_space_bytes() < 64 * gib
    cgroups.write_text("0::/job\n")
    assert resources.available_host_bytes() == min(2 * gib, resources.machine_bytes(), resources.address_space_bytes())
    monkeypatch.setattr(resources, "machine_bytes", lambda: 512 * gib)
    with pytest.raises(resources.ResourceError, match=r"but 2\.0 GiB are available"):
        resources.check_run_fits(specs.load(ROOT / "experiments/grid_5.yaml", "paper",
                                            ["learner.buffer_size=50000000"]))


def test_an_archive_written_into_the_store_s_artifacts_is_refused(tmp_path, capsys):
    from esr_cli.storage.store import Store, content_key

    components = {"kind": "runs", "spec": {"name": "x"}}
    key = content_key(components)
    store = Store(tmp_path / "store")
    store.begin("runs", key, {"name": "x", "key": key, "key_components": components})
    path = store.commit("runs", key, {"kind": "runs", "name": "x", "key": key, "key_components": components})
    for out in (path / "a.tar.gz", path / "new" / "a.tar.gz", tmp_path / "store" / "runs" / "a.tar.gz"):
        assert main(["--store", str(tmp_path / "store"), "export", key[:8], "--out", str(out)]) == 2
        assert "inside the store's runs/ folder" in capsys.readouterr().err
    assert store.verify(path) == [] and not list(tmp_path.rglob("*.tar.gz"))


def test_an_archive_without_out_is_refused_where_the_current_folder_is_in_the_store_s_artifacts(tmp_path, capsys, monkeypatch):
    """`esr export KEY` writes ./KEY8.tar.gz: from inside an artifact (or a kind's folder) that
    would change the store under its manifests, so it is refused as `--out` there is."""
    from esr_cli.storage.store import Store, content_key

    components = {"kind": "runs", "spec": {"name": "x"}}
    key = content_key(components)
    store = Store(tmp_path / "store")
    store.begin("runs", key, {"name": "x", "key": key, "key_components": components})
    path = store.commit("runs", key, {"kind": "runs", "name": "x", "key": key, "key_components": components})
    for here in (path, tmp_path / "store" / "runs"):
        monkeypatch.chdir(here)
        assert main(["--store", str(tmp_path / "store"), "export", key[:8]]) == 2
        err = " ".join(capsys.readouterr().err.split())
        assert f"--out (not given: the current folder): {key[:8]}.tar.gz lies inside the store's runs/ folder" in err
    assert store.verify(path) == [] and not list(tmp_path.rglob("*.tar.gz"))
    monkeypatch.chdir(tmp_path)
    assert main(["--store", str(tmp_path / "store"), "export", key[:8]]) == 0
    assert capsys.readouterr().out.strip() == f"{key[:8]}.tar.gz" and (tmp_path / f"{key[:8]}.tar.gz").is_file()


@pytest.mark.slow  # trains the shared smoke run
@pytest.mark.parametrize("damage, problem", [
    (lambda text: text.replace("  lr: 0.001", "  lr: 0.002"), "its spec.yaml is not the spec its key was computed from"),
    (lambda text: text + "\n: [", "its spec.yaml cannot be read"),
])
def test_a_run_whose_spec_yaml_is_not_its_keys_is_not_evaluated_or_diagnosed(smoke_run, tmp_path, damage, problem):
    """A spec.yaml swapped or broken under a genuine key, in a store: evaluating or diagnosing the
    run would store another spec's numbers as this key's, so both refuse in one line first."""
    import shutil

    _, path, _ = smoke_run
    run = tmp_path / "store" / "runs" / path.parent.name / path.name
    shutil.copytree(path, run)
    (run / "spec.yaml").write_text(damage((run / "spec.yaml").read_text()))
    for command in ("diagnose", "eval"):
        proc = esr(command, path.name[:12], store=tmp_path / "store", check=False)
        assert proc.returncode == 2 and problem in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert f"(`esr verify {run}`)" in proc.stderr  # its folder: whichever store it is in
    assert not (tmp_path / "store" / "diagnoses").exists() and not (tmp_path / "store" / "evals").exists()


def test_an_unreadable_spec_yaml_of_an_unfinished_run_says_to_start_it_over(tmp_path):
    """`esr verify` checks finished artifacts only: an unfinished run's hint is to remove it."""
    from esr_cli.recipes.targets import run_spec
    from esr_cli.storage.store import StoreError

    run = tmp_path / "runs" / "ab" / ("ab" * 16 + ".partial")
    run.mkdir(parents=True)
    (run / "pending.json").write_text(json.dumps({"key": "ab" * 16}))
    (run / "spec.yaml").write_text("name: x\n: [\n")
    with pytest.raises(StoreError, match=rf"its spec.yaml cannot be read.*; the run cannot be read \(remove {re.escape(str(run))} to start it over\)$"):
        run_spec(run)


def test_a_stored_run_keeps_the_human_it_trained_with_when_its_preset_changes(tmp_path, monkeypatch):
    """A run's spec.yaml holds its human's fields as its preset resolved them when it trained;
    read back, the preset's name must not lay a later table of values over them."""
    import yaml

    from esr_cli.common import specs
    from esr_cli.model import spec as spec_model
    from esr_cli.recipes.targets import run_spec
    from esr_cli.storage.transfer import TRAINING_SECTIONS

    trained = specs.load("experiments/cramped_room.yaml", "quick").model_dump(mode="json")
    assert trained["human"]["preset"] == "paper" and trained["human"]["total_steps"] == 1_000_000
    run = tmp_path / "runs" / "ab" / ("ab" * 16)
    run.mkdir(parents=True)
    (run / "spec.yaml").write_text(yaml.safe_dump(trained))
    spec_part = {s: trained[s] for s in TRAINING_SECTIONS}
    spec_part["human"] = {k: v for k, v in trained["human"].items() if k != "preset"}
    (run / "manifest.json").write_text(json.dumps({"kind": "runs", "key": "ab" * 16, "files": {},
                                                   "key_components": {"spec": spec_part, "budget": "quick"}}))
    later = {**spec_model.HUMAN_PRESETS["paper"], "cramped_room": {**spec_model.HUMAN_PRESETS["paper"]["cramped_room"],
                                                                     "total_steps": 2_000_000}}
    monkeypatch.setitem(spec_model.HUMAN_PRESETS, "paper", later)
    assert specs.load("experiments/cramped_room.yaml", "quick").human.total_steps == 2_000_000  # a new run: today's table
    assert run_spec(run).human.total_steps == 1_000_000  # the stored run: the human it trained with


@pytest.mark.parametrize("header, summary, named", [
    ([1, 2], {"completed": True, "steps": 3, "score": 1.0}, "is not a JSON object"),
    ({"started_at": "x"}, {"completed": True, "steps": 3, "score": 1.0}, "has no started_at"),
    ({}, {"completed": "yes", "steps": 3, "score": 1.0}, "has no summary esr wrote"),
    ({}, {"completed": True, "steps": 3, "score": "1"}, "has no summary esr wrote"),
])
def test_a_played_episode_esr_did_not_write_is_one_line_in_plays(tmp_path, capsys, header, summary, named):
    """`esr plays` over a store holding a played episode whose header or summary is not what esr
    writes (another type, a field missing) ends with exit 2 and one line naming it, before any
    table is printed; the listing never trips over it with a KeyError or a format error."""
    from esr_cli.storage.play_log import EPISODE_FILE
    from esr_cli.storage.store import Store, content_key

    store = Store(tmp_path / "s")
    components = {"kind": "play", "spec": {"name": "e"}}
    key = content_key(components)
    written = {"participant": "p", "session": "s", "episode": 0, "robot": "random", "env": {"kind": "gridworld"}, "started_at": 1.0}
    d = store.begin("play", key, {"name": "e", "key": key, "key_components": components})
    (d / EPISODE_FILE).write_text(json.dumps(header if isinstance(header, list) else {**written, **header}))
    store.commit("play", key, {"kind": "play", "name": "e", "key": key, "key_components": components, "summary": summary})
    assert main(["--store", str(tmp_path / "s"), "plays"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "damaged played episode" in lines[0] and named in lines[0], captured.err
    assert key not in captured.out


# ---------------------------------------------------------------- what a store's or another file's text can do
def _copied_run(smoke_run, tmp_path):
    """A copy of the smoke run in a store of its own: (store, run folder, key)."""
    import shutil

    _, path, _ = smoke_run
    store = tmp_path / "store"
    copy_to = store / path.relative_to(path.parents[2])
    shutil.copytree(path, copy_to)
    return store, copy_to, copy_to.name


@pytest.mark.slow
def test_a_stored_name_never_puts_a_curve_outside_the_current_directory(smoke_run, tmp_path):
    """`esr plot curve` names its file after the run; a manifest's name ('../x', '/x') is not a
    path: the file is written in the current directory under a plain name."""
    import subprocess
    import sys

    from conftest import esr_env

    store, run, key = _copied_run(smoke_run, tmp_path)
    (tmp_path / "cwd").mkdir()
    for name in ("../escape/owned", str(tmp_path / "abs" / "owned")):
        manifest = json.loads((run / "manifest.json").read_text())
        manifest["name"] = name
        (run / "manifest.json").write_text(json.dumps(manifest))
        proc = subprocess.run([sys.executable, "-m", "esr_cli.cli.main", "plot", "curve", key[:8]], cwd=tmp_path / "cwd",
                              env=esr_env(store), capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        assert (tmp_path / "cwd" / f"run-{key[:8]}-curve.png").is_file()
        assert not (tmp_path / "escape").exists() and not (tmp_path / "abs").exists()


@pytest.mark.slow
def test_a_curve_of_values_near_the_float_limit_is_drawn_without_warnings(smoke_run, tmp_path):
    store, run, key = _copied_run(smoke_run, tmp_path)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    rows[-1]["return"] = [1.7e308] * len(rows[-1]["return"])
    rows[0]["success"] = [None] * len(rows[0]["success"])
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    proc = esr("plot", "curve", key[:8], "--out", str(tmp_path / "c.png"), store=store, check=False)
    assert proc.returncode == 0 and (tmp_path / "c.png").is_file(), proc.stderr
    assert "Warning" not in proc.stderr and "Traceback" not in proc.stderr


def test_a_file_that_is_not_a_spec_is_never_quoted(tmp_path):
    """A page, suite or extends: can name any file; esr names its mistakes without printing it."""
    for text in ("root:$6$saltsalt$hashhashhash:20228:0:99999:7:::\n", "127.0.0.1 host.secret.example: 1\n",
                 "x: &tok-3f9a1b2c3d4e5f 1\n", "a: {b: 1}\nc: *tok-3f9a1b2c3d4e5f\n",
                 "'pw=hunter2': 1\n'pw=hunter2': 2\n", "? [sk-live-abc]\n: 1\n"):
        with pytest.raises(specs.SpecError) as e:
            specs.load(write(tmp_path, text))
        line = str(e.value)
        assert "\n" not in line
        for secret in ("hashhash", "secret.example", "tok-3f9a", "hunter2", "sk-live"):
            assert secret not in line, line
    with pytest.raises(specs.SpecError, match="password: unknown key"):  # a name is still named
        specs.load(write(tmp_path, VALID + "password: 1\n"))


def test_a_store_s_spec_yaml_is_never_read_through_a_link(tmp_path):
    from esr_cli.storage import transfer

    (tmp_path / "secret.yaml").write_text("x: 1\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / "spec.yaml").symlink_to(tmp_path / "secret.yaml")
    spec, problem = transfer.read_spec_yaml(run)
    assert spec is None and "a symbolic link, not a file" in problem
    (run / "spec.yaml").unlink()
    (run / "spec.yaml").write_text("name: x\n" + "# " + "x" * transfer.MAX_SPEC_YAML_BYTES + "\n")
    spec, problem = transfer.read_spec_yaml(run)
    assert spec is None and "larger than the 65,536 bytes esr reads from a run's spec.yaml" in problem


def test_a_run_whose_metrics_esr_could_not_read_back_is_refused_before_any_work():
    paper = specs.load(ROOT / "experiments/grid_5.yaml", "paper", ["train.seeds=20"])
    resources.check_metrics_readable(paper)  # the paper's 20 seeds x 10,000 epochs: about 50 MiB at most
    many = specs.load(ROOT / "experiments/grid_5.yaml", "paper", ["train.seeds=200"])
    with pytest.raises(resources.ResourceError, match=r"200 seeds would log about .* MiB of metrics, more than the 256 MiB"):
        resources.check_run_fits(many)
    long = specs.load(ROOT / "experiments/grid_5.yaml", "paper", ["train.seeds=1", "train.epochs=500000"])
    with pytest.raises(resources.ResourceError, match=r"500,000 epochs would log more lines of metrics than esr reads back of a run \(at most 131,072 epochs\)"):
        resources.check_run_fits(long)


def test_the_report_and_tables_refuse_what_they_cannot_read_or_write_before_any_work(tmp_path):
    """A pipe or a device as the report to check is never read (it would block, or never end);
    a report is never written into an artifact; a mistyped store is named, not reported on as
    a store without runs."""
    store = tmp_path / "store"
    (store / "runs" / "ab").mkdir(parents=True)
    fifo = tmp_path / "report.md"
    os.mkfifo(fifo)
    page = tmp_path / "page.md"
    page.write_text("# a page\n")
    (store / "runs" / "ab" / "page.md").write_text("# an artifact's page\n")
    for args, problem in (
            (["tables", str(store / "runs" / "ab" / "page.md")], "lies inside the store's runs/ folder"),
            (["paper", "--report", "--no-exact", "--check", "--out", "/dev/zero"], "--out: /dev/zero is not a regular file"),
            (["paper", "--report", "--no-exact", "--check", "--out", str(fifo)], "is not a regular file: nothing to check"),
            (["paper", "--report", "--no-exact", "--out", str(store / "runs" / "ab" / "x.md")], "lies inside the store's runs/ folder"),
            # a folder yet to be made, then `..`: the file would land in the artifact all the same
            (["paper", "--report", "--no-exact", "--out", str(store / "new" / ".." / "runs" / "ab" / "x.md")],
             "lies inside the store's runs/ folder"),
            # a pipe or a device as the report to write is never replaced by a file
            (["paper", "--report", "--no-exact", "--out", str(fifo)], "exists and is not a regular file"),
            (["--store", str(tmp_path / "typo"), "paper", "--report", "--no-exact", "--out", str(tmp_path / "r.md")],
             f"no store at {tmp_path / 'typo'}: no runs to report on"),
            (["--store", str(tmp_path / "typo"), "tables", str(page)], "no runs to draw tables from")):
        proc = esr(*args, store=store, check=False, timeout=60)
        assert proc.returncode == 2 and problem in proc.stderr, (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "r.md").exists() and page.read_text() == "# a page\n" and not (store / "runs" / "ab" / "x.md").exists()
    assert not (store / "new").exists() and stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_an_output_file_is_written_through_its_link_keeps_its_mode_and_is_never_a_device(tmp_path):
    from esr_cli.storage.store import NotAFile, write_output_file

    target = tmp_path / "elsewhere" / "notes.md"
    target.parent.mkdir()
    target.write_text("old")
    target.chmod(0o600)
    link = tmp_path / "notes.md"
    link.symlink_to(target)
    write_output_file(link, b"new")
    assert link.is_symlink() and target.read_text() == "new" and stat.S_IMODE(target.stat().st_mode) == 0o600
    assert [p.name for p in target.parent.iterdir()] == ["notes.md"]  # no temporary file left beside it
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(NotAFile, match="exists and is not a regular file"):
        write_output_file(fifo, b"x")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    fresh = tmp_path / "links.txt"
    write_output_file(fresh, b"secret", mode=0o600)
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o600
