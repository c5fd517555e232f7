"""A run's stored evaluations read back for a table (`esr sweep --results --eval`): the right
evaluation per partner, its statistics recomputed from the per-seed returns, and anything
damaged shown as missing rather than read."""

import pytest

from esr_cli.recipes import eval_lookup
from esr_cli.storage.artifacts import Recipe, ensure
from esr_cli.storage.store import EVAL_KIND, Store

RUN = "ab" * 16


def _eval(store, summary, episodes=8, **components):
    comps = {"kind": "eval", "run": RUN, "episodes": episodes, **components}
    return ensure(Recipe(EVAL_KIND, "e", comps, lambda out, store: summary), store).path


def _summary(per_seed, human="training"):
    return {"human": human, "results": {"sample": {"return_per_seed": per_seed}, "greedy": {"return_per_seed": [0.0] * len(per_seed)}}}


def test_each_partners_evaluation_is_found_and_summarised_from_its_seeds(tmp_path):
    store = Store(tmp_path)
    _eval(store, _summary([10.0, 20.0, 30.0]))
    _eval(store, _summary([4.0, 6.0], "proxy"), human="k" * 32)
    _eval(store, _summary([99.0]), robot_seat=1)  # another seat: not the table's
    _eval(store, _summary([77.0]), episodes=100)  # another episode count
    found = eval_lookup.read_evals(store)
    assert set(found) == {(RUN, "training", 8), (RUN, "proxy", 8), (RUN, "training", 100)}
    cells, missing = eval_lookup.run_cells(found, RUN, 8, ("training", "proxy"))
    # the first policy mode's seeds: mean 20, SE 10 / sqrt(3) = 5.77; proxy mean 5, SE 1
    assert cells["training"].startswith("20.00 ± 5.77; IQM 20.00") and cells["proxy"].startswith("5.00 ± 1.00")
    assert missing == []
    cells, missing = eval_lookup.run_cells(found, "cd" * 16, 8, ("training",))
    assert cells == {"training": "—", "proxy": ""} and missing == ["training"]


@pytest.mark.parametrize("summary", [
    {"human": "training", "results": {"sample": {"return_per_seed": ["10", 2.0]}}},
    {"human": "training", "results": {"sample": {"return_per_seed": [10 ** 400]}}},
    {"human": "training", "results": {"sample": {"return_per_seed": [1.7e308, -1.7e308, 1.0]}}},  # sums overflow
    {"human": "training", "results": {"sample": {"return_per_seed": [float("nan"), 1.0]}}},
    {"human": "training", "results": {"sample": {"return_per_seed": [True]}}},
    {"human": "training", "results": {"sample": {"return_per_seed": []}}},
    {"human": "training", "results": {"sample": "x"}},
    {"human": "training", "results": []},
    {"human": "training"},
])
def test_a_damaged_evaluation_shows_as_missing(tmp_path, summary):
    store = Store(tmp_path)
    _eval(store, summary)
    cells, missing = eval_lookup.run_cells(eval_lookup.read_evals(store), RUN, 8, ("training",))
    assert cells["training"] == "—" and missing == ["training"]


def test_a_proxy_evaluation_whose_summary_names_no_partner_is_passed_over(tmp_path):
    store = Store(tmp_path)
    _eval(store, {**_summary([1.0]), "human": ["proxy"]}, human="k" * 32)
    assert eval_lookup.read_evals(store) == {}


@pytest.mark.parametrize("spec_file, sets, expected", [
    ("experiments/grid_2.yaml", [], ("training",)),
    ("experiments/cramped_room.yaml", [], ("training",)),  # the paper's human: no held-out split of it
    ("experiments/cramped_room.yaml", ["human={kind: bc}"], ("training", "proxy")),
])
def test_a_held_out_proxy_is_shown_only_for_a_bc_human(spec_file, sets, expected):
    from esr_cli.common import specs

    assert eval_lookup.partners(specs.load(spec_file, "quick", sets)) == expected


def test_an_evaluation_kept_without_its_rollout_gif_still_fills_the_table_in_another_store(tmp_path):
    """`esr export --without-checkpoint` of an evaluation leaves its GIF (megabytes) behind: the
    copy verifies (its manifest keeps the GIF's digest) and gives the table the same cell."""
    from conftest import esr

    store, other = Store(tmp_path / "store"), tmp_path / "other"

    def build(out, store):
        (out / "rollout.gif").write_bytes(b"GIF89a" + bytes(1000))
        return _summary([10.0, 20.0, 30.0])

    path = ensure(Recipe(EVAL_KIND, "e", {"kind": "eval", "run": RUN, "episodes": 8}, build), store).path
    archive = tmp_path / "e.tar.gz"
    esr("export", path.name, "--without-checkpoint", "--out", str(archive), store=tmp_path / "store")
    esr("import", str(archive), store=other)
    (copy,) = (other / "evals").glob("*/" + path.name)
    assert not (copy / "rollout.gif").exists() and (copy / "summary.json").exists()
    assert esr("verify", store=other).returncode == 0
    cell = eval_lookup.run_cells(eval_lookup.read_evals(Store(other)), RUN, 8, ("training",))[0]["training"]
    assert cell == eval_lookup.run_cells(eval_lookup.read_evals(store), RUN, 8, ("training",))[0]["training"]
    assert cell.startswith("20.00 ± 5.77")
