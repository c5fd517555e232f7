"""The reproduction report: evidence found by spec, verdicts by the documented rules, and the
real CLI writing docs-style markdown from a store."""

import json
import shlex
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import esr

from esr_cli.common.printing import train_line
from esr_cli.report import reproduction as rep


def _evidence(stem, sets=(), finals=(10.0,), epochs=3000, status="complete", mi=None):
    """A stored run whose every seed returns `finals` over its whole length."""
    spec = rep.claim_spec((stem, tuple(sets)))
    rows = [{"epoch": e, "return": list(finals), **({"mi_estimate": [mi(e)] * len(finals)} if mi else {})}
            for e in range(1, epochs + 1)]
    return rep.Evidence(f"{stem}{len(finals)}{epochs}".ljust(32, "0"), Path("/nowhere"), status, "paper", spec, rows, None)


def _index(*evidence):
    out = {}
    for ev in evidence:
        out.setdefault(rep._without_train(ev.spec), []).append(ev)
    return out


def _claim(text):
    return next(c for c in rep.paper_claims() if c.text == text)


def test_one_seed_verdicts_and_the_comparable_length():
    above = _claim("N = 5: ESR ends above Random")
    index = _index(_evidence("grid_5", finals=(20.0,)), _evidence("grid_5_random", finals=(9.0,)))
    assert rep.judge(above, index).verdict == "indicative: holds (1 seed)"
    index = _index(_evidence("grid_5", finals=(2.0,)), _evidence("grid_5_random", finals=(9.0,)))
    assert rep.judge(above, index).verdict == "indicative: does not hold (1 seed)"
    short = _index(_evidence("grid_5", finals=(20.0,), epochs=2999, status="partial"), _evidence("grid_5_random", finals=(9.0,)))
    finding = rep.judge(above, short)
    assert finding.verdict == rep.NOT_YET and finding.measured.startswith("ESR 20.00 (1 seed) against Random 9.00 (1 seed)")


def test_each_side_of_a_comparison_is_named_with_what_sets_it_apart():
    label = lambda stem, sets=(): rep.run_label(rep.claim_spec((stem, sets)))
    assert label("grid_5") == "ESR"
    assert label("grid_5", rep.QUICK_CHANGES) == "ESR (representation rate 0.001, warm-up 20)"
    assert label("grid_5", rep.NO_ROBOT_ACTION) == "ESR (without aR)"
    assert label("grid_5", rep.GREEDY) == "ESR (critic gamma 0)"
    assert label("grid_5_ave", rep.PUBLISHED_AVE) == "AvE (published)" and label("grid_5_ave") == "AvE"
    assert label("cramped_room") == "ESR"  # Overcooked's own paper rate is not a change
    assert label("cramped_room", ("method.repr_lr=0.001",)) == "ESR (representation rate 0.001)"
    below = _claim("N = 5: AvE ends below Random")
    index = _index(_evidence("grid_5_random", finals=(9.0,)), _evidence("grid_5_ave", rep.PUBLISHED_AVE, finals=(0.0,)))
    assert rep.judge(below, index).measured == "Random 9.00 (1 seed) against AvE (published) 0.00 (1 seed)"


def test_a_run_cell_names_an_accelerator_and_leaves_the_cpu_unsaid():
    ev = _evidence("grid_10", finals=(6.0,) * 10, epochs=1200, status="partial")
    ev.commit, ev.device = "e60b1a13968e", "gpu:NVIDIA H200"
    assert rep._run_cell(ev) == f"`{ev.key[:8]}` (paper; 1,200 epochs of 10,000 (unfinished), 10 seeds, commit e60b1a1, on gpu:NVIDIA H200)"
    ev.device = "cpu:cpu"
    assert rep._run_cell(ev).endswith("10 seeds, commit e60b1a1)")


def test_the_figure_names_the_devices_of_the_runs_it_draws():
    runs = [_evidence("grid_10", finals=(6.0,) * 4), _evidence("grid_5", finals=(9.0,)),
            _evidence("grid_7", finals=(9.0,)), _evidence("grid_2", finals=(9.0,))]
    for ev, device in zip(runs, ("gpu:NVIDIA H200", "cpu:cpu", "cpu:cpu", None)):
        ev.device = device
    line = rep.devices_line(runs)
    # accelerators first, each with its runs named; the CPU's runs counted; an unrecorded device said so
    assert line == (f"Made on: gpu:NVIDIA H200 (1 run: `{runs[0].key[:8]}`); unknown (1 run: `{runs[3].key[:8]}`); "
                    "cpu:cpu (2 runs) (each run's device as its manifest records it).")


def test_a_run_without_its_checkpoint_says_it_starts_again():
    ev = _evidence("grid_10", finals=(6.0,) * 10, epochs=1200, status="partial")
    ev.resumable = False
    assert "1,200 epochs of 10,000 (unfinished; its checkpoint is not in this store), 10 seeds" in rep._run_cell(ev)


def test_several_seeds_against_one_hold_the_single_seed_fixed():
    """A 10-seed GPU run against a 1-seed CPU baseline: the interval resamples the 10 seeds only."""
    above = _claim("N = 10: ESR ends above Random")
    esr10 = _evidence("grid_10", finals=(5.0, 7.0, 2.0, 11.0, 10.0, 6.0, 5.0, 4.0, 8.0, 9.0), epochs=3000)
    finding = rep.judge(above, _index(esr10, _evidence("grid_10_random", finals=(3.5,))))
    # 9 of 10 seeds above 3.5: a resample's P is k/10, k ~ Binomial(10, 0.9); P(k <= 6) = 0.013
    # and P(k <= 7) = 0.070 put the 2.5% quantile at 0.7, so the lower end is above 0.5
    assert "P(improvement) 0.90 [0.70, 1.00]" in finding.measured
    # one side has a single seed: however clear the 10 seeds are, the row is only indicative
    assert finding.verdict == "indicative: holds (10 seeds against 1 seed)"


def test_the_longest_matching_run_is_used_whatever_its_length_or_seeds():
    above = _claim("N = 5: ESR ends above Random")
    index = _index(_evidence("grid_5", finals=(1.0,), epochs=600), _evidence("grid_5", finals=(20.0,), epochs=3000),
                   _evidence("grid_5_random", finals=(9.0,)))
    finding = rep.judge(above, index)
    assert finding.a.epochs_done == 3000
    # the shorter run is not dropped: it is shown beside the verdict with its own comparison
    [(other, measured)] = finding.others
    assert other.epochs_done == 600 and measured == "ESR 1.00 (1 seed) against Random 9.00 (1 seed)"
    # esr's quick-budget changes make another spec: they are a variant, never the paper's ESR
    variant = _index(_evidence("grid_5", rep.QUICK_CHANGES, finals=(20.0,)), _evidence("grid_5_random", finals=(9.0,)))
    finding = rep.judge(above, variant)
    assert finding.a is None and finding.variants[0][1] is not None


def test_several_seeds_use_the_probability_of_improvement_interval():
    above = _claim("N = 7: ESR ends above AvE")
    clear = _index(_evidence("grid_7", finals=(20, 21, 22, 23, 24)),
                   _evidence("grid_7_ave", rep.PUBLISHED_AVE, finals=(1, 2, 3, 4, 5)))
    finding = rep.judge(above, clear)
    assert finding.verdict == "reproduced (5 seeds each)" and "P(improvement) 1.00 [1.00, 1.00]" in finding.measured
    mixed = _index(_evidence("grid_7", finals=(1, 3, 5, 7, 9)),
                   _evidence("grid_7_ave", rep.PUBLISHED_AVE, finals=(2, 4, 6, 8, 10)))
    assert rep.judge(above, mixed).verdict == "inconclusive (5 seeds each)"
    reversed_ = _index(_evidence("grid_7", finals=(1, 2, 3, 4, 5)),
                       _evidence("grid_7_ave", rep.PUBLISHED_AVE, finals=(20, 21, 22, 23, 24)))
    assert rep.judge(above, reversed_).verdict == "not reproduced (5 seeds each)"


def test_mi_claim_needs_a_positive_end_and_a_positive_second_half():
    claim = _claim("N = 2: the MI estimate turns positive and stays positive")
    good = _index(_evidence("grid_2", mi=lambda e: 0.2))
    assert rep.judge(claim, good).verdict == "indicative: holds (1 seed)"
    fading = _index(_evidence("grid_2", mi=lambda e: 0.2 if e < 1000 else -0.001))
    assert rep.judge(claim, fading).verdict == "indicative: does not hold (1 seed)"


@pytest.mark.slow
def test_cli_writes_the_report_from_a_store(tmp_path):
    """One-epoch runs of the paper's own grid_2 specs (only `train` shortened) are evidence for
    the N = 2 statements; smoke-budget runs change the learner and are not."""
    store = tmp_path / "store"
    short = ["--set", "train.epochs=1", "--set", "train.num_envs=4", "--set", "train.seeds=1", "--set", "train.chunk_epochs=1"]
    run_path = Path(esr("train", "experiments/grid_2.yaml", *short, store=store).stdout.strip())
    esr("train", "experiments/grid_2_random.yaml", *short, store=store)
    esr("train", "experiments/grid_2.yaml", "--budget", "smoke", store=store)
    human = Path(esr("train", "experiments/grid_2.yaml", *short, "--set", "method.future=human", store=store).stdout.strip())
    out = tmp_path / "docs" / "reproduction.md"
    proc = esr("paper", "--report", "--out", str(out), "--no-exact", "--json", store=store)
    verdicts = json.loads(proc.stdout)
    row = next(v for v in verdicts if v["statement"] == "N = 2: ESR ends above Random")
    assert row["a"]["key"] == run_path.name and row["a"]["epochs"] == 1 and row["b"]["epochs"] == 1
    assert row["verdict"] == rep.NOT_YET
    # esr's variant travels with the statements of its spec, set against the paper's setting
    [variant] = row["variants"]
    assert variant["variant"] == "method.future=human" and variant["run"]["key"] == human.name
    assert variant["which_way"] == rep.NOT_YET and variant["measured"].startswith("ESR (human future) ")
    assert len(row["a"]["final_return"]["per_seed"]) == 1  # per-seed finals travel with every verdict
    assert np.isfinite(row["a"]["final_return"]["mean"])
    text = out.read_text()
    assert "| N = 2: ESR ends above Random |" in text and f"`{run_path.name[:8]}`" in text
    assert "## esr's variants against the paper's setting" in text
    assert sum(line.startswith("| grid_2: `method.future=human` |") for line in text.splitlines()) == 1
    assert "**Summary:** 38 statements" in text
    assert "train experiments/grid_2.yaml --budget paper --set train.epochs=1 --set train.num_envs=4 --set train.seeds=1 --set train.chunk_epochs=1" in text
    assert len(list(Path(store).glob("runs/*/*/manifest.json"))) == 4  # the report trained nothing
    # --check: the committed report agrees with the store, whatever the generated-on line says ...
    out.write_text(out.read_text().replace("Generated by `esr", "Generated by `esr --store elsewhere", 1))
    assert esr("paper", "--report", "--out", str(out), "--no-exact", "--check", store=store).returncode == 0
    # ... until a run's metrics change: the check fails, names the stale file and shows the change
    metrics = run_path / "metrics.jsonl"
    rows = [json.loads(line) for line in metrics.read_text().splitlines()]
    rows[-1]["return"] = [123.45]
    metrics.write_text("".join(json.dumps(r) + "\n" for r in rows))
    stale = esr("paper", "--report", "--out", str(out), "--no-exact", "--check", store=store, check=False)
    assert stale.returncode == 1 and "is stale" in stale.stderr and "+| N = 2: ESR ends above Random" in stale.stderr
    assert "123.45" in stale.stderr and "123.45" not in out.read_text()  # --check writes nothing


def test_the_estimator_check_takes_the_longest_finished_n2_esr_run_that_learned():
    random = _evidence("grid_2_random", finals=(13.0,))
    paper = _evidence("grid_2", finals=(17.0,), epochs=1000)
    quick = _evidence("grid_2", rep.QUICK_CHANGES, finals=(35.0,), epochs=1000)
    assert rep.estimator_run(_index(random, quick, paper)) is paper  # a tie goes to the paper's settings
    assert rep.estimator_run(_index(random, paper, quick)) is paper
    longer = _evidence("grid_2", rep.QUICK_CHANGES, finals=(35.0,), epochs=1500)
    assert rep.estimator_run(_index(random, paper, longer)) is longer
    below = _evidence("grid_2", finals=(9.0,), epochs=3000)
    unfinished = _evidence("grid_2", rep.QUICK_CHANGES, finals=(35.0,), epochs=2000, status="partial")
    larger_grid = _evidence("grid_5", finals=(30.0,), epochs=3000)
    assert rep.estimator_run(_index(random, paper, below, unfinished, larger_grid)) is paper
    assert rep.estimator_run(_index(paper)) is None  # no Random run to have learned against


def test_the_estimator_check_compares_a_run_with_the_random_robot_of_its_own_gridworld():
    """A run on a gridworld no paper spec describes (one block, from the centre) is compared with
    the Random run on that gridworld, never with the paper's, and needs no spec of its own."""
    one_block = ("env.blocks=1", "env.start=center")
    random_1 = _evidence("grid_2_random", one_block, finals=(25.0,))
    below_its_random = _evidence("grid_2", one_block, finals=(20.0,), epochs=4000)
    random_2 = _evidence("grid_2_random", finals=(13.0,))
    paper = _evidence("grid_2", finals=(17.0,), epochs=1000)
    assert rep.estimator_run(_index(random_2, random_1, below_its_random, paper)) is paper
    assert rep.estimator_run(_index(random_2, below_its_random)) is None  # the paper's Random is another gridworld's
    above_its_random = _evidence("grid_2", one_block, finals=(30.0,), epochs=4000)
    assert rep.estimator_run(_index(random_2, random_1, above_its_random, paper)) is above_its_random


class _Figures:
    """A store holding the estimator scatters in `folders` (key -> folder), and nothing else."""

    def __init__(self, folders=None):
        self.folders = folders or {}

    def lookup(self, kind, key):
        return self.folders.get(key) if kind == rep.FIGURE_KIND else None


def test_the_estimator_section_shows_the_stored_checks_of_the_chosen_run(monkeypatch, tmp_path):
    random = _evidence("grid_2_random", finals=(13.0,))
    paper = _evidence("grid_2", finals=(17.0,), epochs=1000)
    section = lambda index, store=_Figures(): rep.estimator_section(index, store, None, False, tmp_path / "img")

    # no run that learned: the section says when it fills in
    assert "this section fills in once one has" in "\n".join(section(_index(paper)))

    asked = []
    checks = {"trained": rep.SeedCheck(), "uniform": rep.SeedCheck()}
    monkeypatch.setattr(rep, "_stored_estimator_check", lambda ev, store: asked.append(ev) or (checks["trained"], checks["uniform"]))
    text = "\n".join(section(_index(random, paper)))
    assert asked == [paper] and "not computed (run `esr paper --report` without `--no-exact`)" in text

    checks["trained"] = rep.SeedCheck(exact="a" * 32, effective_empowerment=0.177, spearman_all=0.342, pairs=934500,
                                      spearman_visited=0.821, visited_pairs=28, estimator="b" * 32)
    checks["uniform"] = rep.SeedCheck(exact="c" * 32, effective_empowerment=0.051)
    lines = section(_index(random, paper))
    assert f"On ESR run `{paper.key[:8]}` (N = 2," in "\n".join(lines)
    assert "| Spearman (ESR's reward, exact MI), all 934,500 (state, robot action) pairs | 0.342 |" in lines
    assert "| the same over the 28 pairs holding 99% of the trained robot's discounted occupancy | 0.821 |" in lines
    assert "| the human's exact effective empowerment under the trained robot | 0.177 nats |" in lines
    assert "| the same under a uniform robot | 0.051 nats |" in lines
    assert "Artifacts: exact `aaaaaaaa` (trained), `cccccccc` (uniform), estimator check `bbbbbbbb`." in lines
    assert not any("img/reproduction_estimator.png" in line for line in lines)  # no scatter stored, none shown

    # a stored scatter is copied beside the report and shown, with how many of the pairs it draws
    scatter = tmp_path / "scatter"
    scatter.mkdir()
    (scatter / "estimator.png").write_bytes(b"\x89PNG not really")
    shown = section(_index(random, paper), _Figures({"b" * 32: scatter}))
    assert "![ESR's reward against the exact MI](img/reproduction_estimator.png)" in shown
    assert (tmp_path / "img" / "reproduction_estimator.png").read_bytes() == b"\x89PNG not really"
    assert any("of the 934,500 drawn at random" in line for line in shown)

    # a check that was not made over every pair has no all-pairs row, and keeps the others
    checks["trained"] = replace(checks["trained"], spearman_all=None, pairs=None)
    partial = section(_index(random, paper))
    assert not any(line.startswith("| Spearman (ESR's reward, exact MI), all") for line in partial)
    assert "| the same under a uniform robot | 0.051 nats |" in partial


def test_an_mi_estimate_stuck_near_zero_is_not_positive():
    claim = _claim("N = 5: the MI estimate turns positive and stays positive")
    stuck = _index(_evidence("grid_5", mi=lambda e: 0.002))
    assert rep.judge(claim, stuck).verdict == "indicative: does not hold (1 seed)"


def test_the_command_that_made_a_run_resolves_to_its_spec():
    """The report's command for a run: its experiments/ file and the --set values that turn it
    into the stored spec, at the run's budget (a quick run's own budget changes are not repeated)."""
    sets = ["train.epochs=3000", "train.seeds=1", "method.variant=original"]
    spec = rep.specs.load(rep.EXPERIMENTS / "grid_5_ave.yaml", "paper", sets)
    file, found = rep.train_overrides(spec, "paper")
    assert file.name == "grid_5_ave.yaml" and sorted(found) == sorted(sets)
    quick = rep.specs.load(rep.EXPERIMENTS / "grid_7.yaml", "quick", ["train.epochs=200", "train.seeds=[3, 4]", "method.future=human"])
    file, found = rep.train_overrides(quick, "quick")
    assert sorted(found) == ["method.future=human", "train.epochs=200", "train.seeds=[3, 4]"]
    assert rep.specs.load(file, "quick", found).training_part() == quick.training_part()
    renamed = rep.specs.load(rep.EXPERIMENTS / "grid_2.yaml", "paper", ["name=my_grid"])
    assert rep.train_overrides(renamed, "paper") is None  # no experiments/my_grid.yaml
    ev = rep.Evidence("0" * 32, Path("/store/runs/00/x"), "partial", "paper", spec, [{"epoch": 1, "return": [1.0]}], "abc1234")
    assert rep.train_command(ev, rep.Store(Path("/store"))) == (
        "esr --store /store train experiments/grid_5_ave.yaml --budget paper"
        " --set method.variant=original --set train.epochs=3000 --set train.seeds=1")
    seeds = rep.specs.load(rep.EXPERIMENTS / "grid_5.yaml", "paper", ["train.seeds=[1]"])
    line = rep.train_command(replace(ev, spec=seeds), rep.Store(Path("/my store")))
    # pasted into a shell: a glob and a space in the store's path reach esr as they were
    assert shlex.split(line) == ["esr", "--store", "/my store", "train", "experiments/grid_5.yaml", "--budget", "paper",
                                 "--set", "train.seeds=[1]"]


def test_a_train_line_survives_the_shell_whatever_the_values():
    sets = ["name=it's mine", "train.seeds=[0, 1]", "env.blocks=5", "method.note=$HOME `x` *"]
    line = train_line("esr", "my specs/a.yaml", "paper", sets)
    assert shlex.split(line) == ["esr", "train", "my specs/a.yaml", "--budget", "paper",
                                 *(w for s in sets for w in ("--set", s))]
    assert "--set env.blocks=5" in line  # a plain value stays unquoted, as a person would type it


PROGRAM = json.dumps({"code": "5" * 32, "toolchain": {"backend": "cpu", "jax": "0.10.2", "jaxlib": "0.10.2"}})


def test_finished_runs_that_differ_only_in_their_seeds_are_pooled():
    """Two one-seed runs of one length, one training program and one device, seeds 0 and 1: one
    run of two seeds, never an arbitrary pick of one, whichever commits they were started from;
    another program (code or toolchain), another device, a repeated seed or an unknown program is
    not pooled."""
    above = _claim("coord_ring: ESR ends above Random")
    seed0 = _evidence("coord_ring", ("train.seeds=[0]",), finals=(0.06,), epochs=10000)
    seed1 = _evidence("coord_ring", ("train.seeds=[1]",), finals=(19.5,), epochs=10000)
    random = _evidence("coord_ring_random", ("train.seeds=1",), finals=(16.39,), epochs=10000)
    seed0.key, seed1.key = "a" * 32, "b" * 32
    for ev in (seed0, seed1, random):
        ev.commit, ev.program, ev.device = "2b82b53", PROGRAM, "cpu:cpu"
    seed1.commit = "af75888"  # another checkout of the same training code
    finding = rep.judge(above, _index(seed1, seed0, random))
    assert finding.a.seeds == 2 and [p.key for p in finding.a.parts] == [seed0.key, seed1.key]
    assert finding.a.finals()["per_seed"] == pytest.approx([0.06, 19.5]) and finding.others == []
    assert finding.verdict == "indicative: open (2 seeds against 1 seed)"  # P(improvement) 0.5 [0, 1] against one Random seed
    assert rep._run_cell(finding.a).startswith("seeds pooled from `aaaaaaaa` (paper; 10,000 epochs, 1 seed")
    apart = [{"program": PROGRAM.replace("5" * 32, "6" * 32)}, {"program": PROGRAM.replace("0.10.2", "0.10.3", 1)},
             {"device": "gpu:NVIDIA H200"}, {"program": None}, {"spec": seed0.spec}]  # the last: the same seed twice
    for change in apart:
        finding = rep.judge(above, _index(replace(seed1, **change), seed0, random))
        assert finding.a.parts == () and len(finding.others) == 1, change


def test_a_runs_program_is_read_from_its_key_components():
    toolchain = {"backend": "cpu", "jax": "0.10.2", "jaxlib": "0.10.2"}
    assert rep._program({"key_components": {"code": "5" * 32, "toolchain": toolchain}}) == PROGRAM
    for damaged in ({}, {"key_components": []}, {"key_components": {"code": "5" * 31, "toolchain": toolchain}},
                    {"key_components": {"code": "X" * 32, "toolchain": toolchain}}, {"key_components": {"code": "5" * 32}},
                    {"key_components": {"code": 5, "toolchain": toolchain}}):
        assert rep._program(damaged) is None, damaged


def test_the_pool_with_most_seeds_is_chosen_whichever_run_is_listed_first():
    """An older program's one-seed run beside three one-seed runs of a newer one (seeds 0, 1
    and 2): the three are the evidence, the older run is listed beside them."""
    above = _claim("coord_ring: ESR ends above Random")
    old = _evidence("coord_ring", ("train.seeds=1",), finals=(3.0,), epochs=10000)
    old.key, old.commit, old.program = "c" * 32, "2b82b53", PROGRAM.replace("5" * 32, "4" * 32)
    new = []
    for seed, final in enumerate((10.0, 12.0, 14.0)):
        ev = _evidence("coord_ring", (f"train.seeds=[{seed}]",), finals=(final,), epochs=10000)
        ev.key, ev.commit, ev.program = str(seed) * 32, "3a61962", PROGRAM
        new.append(ev)
    random = _evidence("coord_ring_random", ("train.seeds=1",), finals=(16.39,), epochs=10000)
    finding = rep.judge(above, _index(old, *new, random))
    assert finding.a.seeds == 3 and [p.key for p in finding.a.parts] == [e.key for e in new]
    assert finding.a.finals()["per_seed"] == pytest.approx([10.0, 12.0, 14.0])
    assert [o[0].key for o in finding.others] == [old.key]


def _components_of(spec_file):
    """The key components a run's spec.yaml must match (what training keys it by)."""
    import yaml

    from esr_cli.storage.transfer import TRAINING_SECTIONS

    raw = yaml.safe_load(spec_file.read_text())
    part = {s: raw.get(s) for s in TRAINING_SECTIONS}
    part["human"] = {k: v for k, v in raw["human"].items() if k != "preset"}
    return {"spec": part, "budget": raw["budget"]}


def test_a_run_resumed_elsewhere_names_where_it_started_and_every_device(tmp_path):
    """The commit is the one it started from (flagged when that checkout's esr_cli/ had edits);
    the devices are every one it ran on, in order."""
    from esr_cli.common import specs
    from esr_cli.storage.store import Store

    spec = rep.claim_spec(("grid_10", ()))
    key = "ab" * 16
    run = tmp_path / "runs" / key[:2] / key
    run.mkdir(parents=True)
    (run / "spec.yaml").write_text(specs.to_yaml(spec))
    (run / "metrics.jsonl").write_text("".join(json.dumps({"epoch": e, "return": [5.0]}) + "\n" for e in (1, 2)))
    sessions = [{"commit": "a" * 40, "dirty": True, "device": "gpu:NVIDIA H100"},
                {"commit": "b" * 40, "dirty": False, "device": "gpu:NVIDIA H200"},
                {"commit": "b" * 40, "dirty": False, "device": "gpu:NVIDIA H200"}]
    manifest = {"kind": "runs", "key": key, "files": {}, "budget": "paper", "sessions": sessions,
                "provenance": {"git": {"commit": "b" * 40}, "device": "gpu:NVIDIA H200"},
                "key_components": _components_of(run / "spec.yaml")}
    (run / "manifest.json").write_text(json.dumps(manifest))
    [ev] = [e for evs in rep.index_store(Store(tmp_path)).values() for e in evs]
    assert ev.commit == "a" * 40 and ev.device == "gpu:NVIDIA H100, then gpu:NVIDIA H200"
    assert rep._run_cell(ev).endswith("commit aaaaaaa (esr_cli/ modified), on gpu:NVIDIA H100, then gpu:NVIDIA H200)")
    manifest.pop("sessions")  # made before sessions were recorded: the finishing session's commit and device
    (run / "manifest.json").write_text(json.dumps(manifest))
    [ev] = [e for evs in rep.index_store(Store(tmp_path)).values() for e in evs]
    assert (ev.commit, ev.device, ev.commit_label) == ("b" * 40, "gpu:NVIDIA H200", "bbbbbbb")


def test_a_side_without_a_final_score_gives_no_verdict():
    above = _claim("N = 5: ESR ends above Random")
    index = _index(_evidence("grid_5", finals=(float("nan"),)), _evidence("grid_5_random", finals=(9.0,)))
    finding = rep.judge(above, index)
    assert finding.verdict == "indicative: open (0 seeds against 1 seed)" and finding.measured.startswith("ESR no value")
    several = _index(_evidence("grid_5", finals=(20.0, 21.0, float("nan"))), _evidence("grid_5_random", finals=(9.0,)))
    finding = rep.judge(above, several)
    assert finding.verdict == "indicative: holds (2 seeds against 1 seed)"  # the seed without a score counts nowhere
    assert "(1 of 3 seeds without a final score)" in finding.measured


@pytest.mark.parametrize("seeds_a, seeds_b, verdict", [
    ((20.0,), (9.0,), "indicative: holds (1 seed)"),
    ((20.0, 21.0), (9.0, 8.0), "indicative: holds (2 seeds each)"),
    ((20.0, 21.0, 22.0), (9.0, 8.0), "indicative: holds (3 seeds against 2 seeds)"),
    ((20.0, 21.0, 22.0), (9.0, 8.0, 10.0), "reproduced (3 seeds each)"),
    ((2.0, 1.0, 3.0), (9.0, 8.0, 10.0), "not reproduced (3 seeds each)"),
    ((1.0, 9.5, 3.0, 12.0), (9.0, 8.0, 10.0), "inconclusive (4 seeds against 3 seeds)"),
    ((1.0, 9.5), (9.0, 8.0), "indicative: open (2 seeds each)"),
])
def test_a_verdict_needs_three_seeds_on_every_side(seeds_a, seeds_b, verdict):
    above = _claim("N = 5: ESR ends above Random")
    index = _index(_evidence("grid_5", finals=seeds_a), _evidence("grid_5_random", finals=seeds_b))
    assert rep.judge(above, index).verdict == verdict


def test_similar_is_an_equivalence_test_with_a_stated_margin():
    """N = 2: ESR and AvE end level. Margin: 15% of the larger mean."""
    level = _claim("N = 2: ESR and AvE end level")
    ave = lambda finals: _evidence("grid_2_ave", rep.PUBLISHED_AVE, finals=finals)  # noqa: E731
    # 20 vs 19.5 with tight seeds: the 90% interval of the difference is inside +-3.0
    close = rep.judge(level, _index(_evidence("grid_2", finals=(19.9, 20.0, 20.1)), ave((19.4, 19.5, 19.6))))
    assert close.verdict == "reproduced (3 seeds each)" and "margin ±3.00" in close.measured
    # 20 vs 10: the interval is wholly outside the margin
    apart = rep.judge(level, _index(_evidence("grid_2", finals=(19.9, 20.0, 20.1)), ave((9.9, 10.0, 10.1))))
    assert apart.verdict == "not reproduced (3 seeds each)"
    # equal means but seeds spread far wider than the margin: equivalence is not shown (the old
    # rule, an improvement interval containing 0.5, called this similar)
    wide = rep.judge(level, _index(_evidence("grid_2", finals=(5.0, 20.0, 35.0)), ave((4.0, 21.0, 35.0))))
    assert wide.verdict == "inconclusive (3 seeds each)"
    # one seed each: the difference itself against the margin, and only indicative
    one = rep.judge(level, _index(_evidence("grid_2", finals=(20.0,)), ave((18.0,))))
    assert one.verdict == "indicative: holds (1 seed)" and "difference +2.00, margin ±3.00" in one.measured


def test_the_mean_difference_interval_matches_a_hand_computed_case():
    from esr_cli.common.stats import mean_difference_ci

    # one seed each: no interval; a constant sample resampled gives a point interval
    assert mean_difference_ci([5.0], [3.0]) == (2.0, None, None)
    diff, low, high = mean_difference_ci([5.0, 5.0, 5.0], [3.0])
    assert (diff, low, high) == (2.0, 2.0, 2.0)
    # X in {0, 10}: resampled means are k * 10 / 2 for k ~ Binomial(2, 1/2): 0, 5 or 10, so the
    # 90% percentile interval of mean(X) - 1 is [-1, 9]
    diff, low, high = mean_difference_ci([0.0, 10.0], [1.0])
    assert diff == 4.0 and (low, high) == (-1.0, 9.0)


def test_goal_inference_claims_use_du_et_al_and_show_the_exact_posterior_as_esrs():
    claim = _claim("N = 7: ESR ends above Goal Inference")
    assert rep.claim_spec(claim.b).method.variant == "original"
    index = _index(_evidence("grid_7", finals=(22.0, 23.0, 24.0)),
                   _evidence("grid_7_goal_inference", rep.PUBLISHED_GOAL_INFERENCE, finals=(15.0, 15.5, 16.0)),
                   _evidence("grid_7_goal_inference", finals=(32.0, 33.0, 32.5)))
    finding = rep.judge(claim, index)
    assert finding.verdict == "reproduced (3 seeds each)"
    assert "against Goal Inference (published) 15.50" in finding.measured
    [row] = finding.baselines
    assert row.label == "esr's Goal Inference (exact posterior)" and row.verdict == "not reproduced (3 seeds each)"
    # the verdict depends on which baseline is used, and the row says so
    assert "the verdict depends on the baseline: against esr's Goal Inference (exact posterior)" in finding.measured
    only_published = _index(index[rep._without_train(rep.claim_spec(claim.a))][0],
                            _evidence("grid_7_goal_inference", rep.PUBLISHED_GOAL_INFERENCE, finals=(15.0, 15.5, 16.0)))
    assert "depends on the baseline" not in rep.judge(claim, only_published).measured


def test_the_summary_counts_each_tier():
    claims = [_claim("N = 5: ESR ends above Random"), _claim("N = 7: ESR ends above Random")]
    index = _index(_evidence("grid_5", finals=(20.0, 21.0, 22.0)), _evidence("grid_5_random", finals=(9.0, 8.0, 10.0)),
                   _evidence("grid_7", finals=(20.0,)), _evidence("grid_7_random", finals=(9.0,)))
    findings = [rep.judge(c, index) for c in claims]
    line = rep.summary_line(findings)
    assert line.startswith("2 statements: 1 reproduced, 0 not reproduced and 0 inconclusive with at least 3 seeds")
    assert "1 indicative on fewer seeds (1 holding, 0 not holding, 0 open); 0 not yet" in line


def test_the_report_figure_colours_by_method_and_dashes_esrs_variants():
    from esr_cli.report.figures import METHOD_COLORS
    from esr_cli.report.reproduction_figure import iqm_band, line_style

    style = lambda stem, sets=(): line_style(rep.claim_spec((stem, sets)))  # noqa: E731
    assert style("grid_5") == (METHOD_COLORS["esr"], "-")
    assert style("grid_5", rep.QUICK_CHANGES) == (METHOD_COLORS["esr"], "--")
    assert style("grid_5_goal_inference", rep.PUBLISHED_GOAL_INFERENCE) == (METHOD_COLORS["goal_inference"], "-")
    assert style("grid_5_goal_inference") == (METHOD_COLORS["goal_inference"], "--")  # esr's exact posterior
    assert style("grid_5_ave", rep.PUBLISHED_AVE) == (METHOD_COLORS["ave"], "-")
    assert style("grid_5_ave") == (METHOD_COLORS["ave"], "--")
    assert style("grid_5", rep.NO_ROBOT_ACTION)[0] not in METHOD_COLORS.values()
    # Overcooked: the paper's human solid, esr's MLP clone dotted, in the method's colour
    assert style("cramped_room_random") == (METHOD_COLORS["random"], "-")
    assert style("cramped_room_random", ('human={"kind": "bc"}',)) == (METHOD_COLORS["random"], ":")
    assert style("cramped_room", ('human={"kind": "bc"}',)) == (METHOD_COLORS["esr"], ":")
    assert style("cramped_room", ('human={"kind": "bc"}', "method.future=human")) == (style("grid_5", ("method.future=human",))[0], ":")
    # the IQM of 4 seeds is the mean of the middle two; the band lies within the seeds' range
    centre, low, high = iqm_band(np.array([[1.0, 2.0, 3.0, 10.0], [5.0, 5.0, 5.0, 5.0]]))
    assert centre.tolist() == [2.5, 5.0] and low[1] == high[1] == 5.0
    assert 1.0 <= low[0] <= centre[0] <= high[0] <= 10.0
    one, lo1, hi1 = iqm_band(np.array([[3.0], [4.0]]))
    assert one.tolist() == lo1.tolist() == hi1.tolist() == [3.0, 4.0]


def test_a_run_with_another_kind_of_human_is_made_again_by_a_whole_section_override():
    from esr_cli.common import specs
    from esr_cli.report.reproduction import train_overrides

    spec = specs.load("experiments/cramped_room.yaml", "smoke", ["human={kind: ppo, total_steps: 4096}", "train.seeds=2"])
    file, sets = train_overrides(spec, "smoke")
    assert file.name == "cramped_room.yaml" and any(s.startswith("human={") for s in sets) and "train.seeds=2" in sets
    assert specs.load(file, "smoke", sets).training_part() == spec.training_part()


def test_overcooked_claims_are_judged_with_the_paper_human_and_show_the_clone_s_runs_apart():
    """The layout specs play with the paper's human; runs made with esr's MLP clone (before the
    specs named the paper's) are a row of their own under the claim, judged on their own pair,
    never in the paper's place. AvE is the published one, esr's fixed AvE an extra row."""
    claim = _claim("coord_ring: ESR ends above Random")
    clone = rep.CLONE_HUMAN
    assert rep.run_label(rep.claim_spec(("coord_ring", clone))) == "ESR (bc human)"
    assert rep.run_label(rep.claim_spec(("coord_ring", ()))) == "ESR"
    assert rep.run_label(rep.claim_spec(("coord_ring", ("human.per_seed=true",)))) == "ESR"  # one per seed: still the paper's
    earlier = _index(_evidence("coord_ring", clone, finals=(9.0, 10.0, 11.0), epochs=10_000),
                     _evidence("coord_ring_random", clone, finals=(16.0, 17.0, 15.0), epochs=10_000))
    finding = rep.judge(claim, earlier)
    assert finding.verdict == rep.NOT_YET and finding.measured == "not run"  # nothing with the paper's human
    [row] = finding.conditions
    assert row.label == "with esr's MLP clone as the human, not the paper's"
    assert row.verdict == "not reproduced (3 seeds each)"
    assert row.measured.startswith("ESR (bc human) 10.00 ± 0.58") and "against Random (bc human) 16.00" in row.measured
    both = _index(*[ev for evs in earlier.values() for ev in evs],
                  _evidence("coord_ring", finals=(9.0, 10.0, 11.0), epochs=10_000),
                  _evidence("coord_ring_random", finals=(6.0, 7.0, 5.0), epochs=10_000))
    finding = rep.judge(claim, both)
    assert finding.verdict == "reproduced (3 seeds each)" and finding.conditions[0].verdict == "not reproduced (3 seeds each)"
    assert {e.key for e in finding.evidence()} == {e.key for evs in both.values() for e in evs}
    ave = _claim("coord_ring: ESR ends above AvE")
    assert rep.claim_spec(ave.b).method.variant == "original" and ave.baseline_variants == [("coord_ring_ave", ())]


def test_a_run_of_a_preset_section_is_made_again_from_its_kind():
    """A run made with another human than the file's preset (whose fields a --set beside it
    cannot change) is made again by restarting the section from its kind, then its fields."""
    from esr_cli.common import specs
    from esr_cli.report.reproduction import train_overrides

    for sets in (["human={kind: bc}", "train.seeds=[1]"], ["human={kind: bc, stay_weight: 0.3}"], ["human.seed=4"]):
        spec = specs.load("experiments/coord_ring.yaml", "paper", sets)
        file, found = train_overrides(spec, "paper")
        assert file.name == "coord_ring.yaml" and specs.load(file, "paper", found).training_part() == spec.training_part()
    spec = specs.load("experiments/coord_ring.yaml", "paper", ["human={kind: bc, stay_weight: 0.3}"])
    assert train_overrides(spec, "paper")[1] == ['human={"kind": "bc"}', "human.stay_weight=0.3"]


def test_a_variant_is_set_against_the_paper_setting_of_its_spec_once():
    """esr's variant and the paper's ESR at N = 5: three seeds each wholly above is 'higher', with
    the final MI of both; the pair is shown once however many statements show the variant."""
    paper = _evidence("grid_5", finals=(20.0, 21.0, 22.0), mi=lambda e: 0.0)
    human = _evidence("grid_5", rep.FUTURE_HUMAN, finals=(30.0, 31.0, 32.0), mi=lambda e: 0.15)
    index = _index(paper, human, _evidence("grid_5_random", finals=(9.0, 9.0, 9.0)))
    findings = [rep.judge(c, index) for c in rep.paper_claims() if c.a[0] == "grid_5"]
    assert sum(1 for f in findings for _, ev, _ in f.variants if ev is human) > 1
    [row] = rep.variant_rows(findings)
    assert row.variant is human and row.paper is paper and row.label == "method.future=human"
    # every variant seed above every paper seed: P(improvement) 1 in every resample
    assert row.measured.endswith("; P(improvement) 1.00 [1.00, 1.00]")
    assert row.measured.startswith("ESR (human future) 31.00 ± 0.58")
    assert row.mi == "+0.150 against +0.000" and row.reading == "higher (3 seeds each)"
    [line] = [x for x in rep.variant_section(findings) if x.startswith("| grid_5: `method.future=human`")]
    assert line.endswith("| higher (3 seeds each) |")


def test_a_variant_reading_is_indicative_below_three_seeds_and_waits_for_the_length():
    paper = _evidence("grid_10", finals=(9.0, 10.0, 9.5, 10.5))
    human = _evidence("grid_10", rep.FUTURE_HUMAN, finals=(14.0, 23.0))
    claim = _claim("N = 10: ESR ends above Random")
    finding = rep.judge(claim, _index(paper, human, _evidence("grid_10_random", finals=(3.5,))))
    [row] = rep.variant_rows([finding])
    assert row.reading == "indicative: higher (2 seeds against 4 seeds)" and row.mi == "—"
    # seeds on both sides of the paper's: open, whatever the means say
    mixed = _evidence("grid_10", rep.FUTURE_HUMAN, finals=(5.0, 12.0, 30.0))
    [row] = rep.variant_rows([rep.judge(claim, _index(paper, mixed, _evidence("grid_10_random", finals=(3.5,))))])
    assert row.reading == "not distinguishable (3 seeds against 4 seeds)"
    short = _evidence("grid_10", rep.FUTURE_HUMAN, finals=(30.0, 31.0, 32.0), epochs=2000, status="partial")
    [row] = rep.variant_rows([rep.judge(claim, _index(paper, short, _evidence("grid_10_random", finals=(3.5,))))])
    assert row.reading == rep.NOT_YET
