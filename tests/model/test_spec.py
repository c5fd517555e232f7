"""Spec loading and validation: every bad spec names file, key path and problem, exits 2,
and leaves the store as it was."""

import re
from pathlib import Path

import pytest
import yaml
from conftest import ROOT

from esr_cli.cli.main import main
from esr_cli.common import specs
from esr_cli.model import spec as spec_model

EXPERIMENTS = sorted(Path("experiments").glob("*.yaml"))
GOOD = """
name: t
env: {kind: gridworld, size: 5, blocks: 2}
human: {kind: noisy_greedy}
method: {kind: esr}
"""


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda p: p.stem)
@pytest.mark.parametrize("budget", spec_model.BUDGETS)
def test_every_experiment_loads_at_every_budget(path, budget):
    spec = specs.load(path, budget)
    assert spec.budget == budget


def test_defaults_filled_and_frozen(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(GOOD)
    spec = specs.load(f)
    assert spec.learner.batch_size == 256 and spec.method.repr_dim == 32 and spec.train.seeds == (0, 1, 2, 3, 4)
    with pytest.raises(Exception):
        spec.learner.gamma = 0.5  # frozen


def test_budgets_and_overrides(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(GOOD + "budgets: {quick: {train.epochs: 7}}\n")
    assert specs.load(f, "quick").train.epochs == 7
    assert specs.load(f, "smoke").train.epochs == specs.DEFAULT_BUDGETS["smoke"]["train.epochs"]
    s = specs.load(f, "paper", ["learner.gamma=0", "train.seeds=3", "method.repr_lr=1e-5"])
    assert s.learner.gamma == 0.0 and s.train.seeds == (0, 1, 2) and s.method.repr_lr == 1e-5
    assert specs.load(f, "paper", ["train.seeds=[4, 9]"]).train.seeds == (4, 9)


def test_yaml_exponent_without_dot_is_a_number(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(GOOD.replace("method: {kind: esr}", "method: {kind: esr, repr_lr: 3e-5}"))
    assert specs.load(f).method.repr_lr == 3e-5


def test_training_part_excludes_name_and_eval(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(GOOD)
    a = specs.load(f)
    b = specs.load(f, "paper", ["name=other", "eval.episodes=5"])
    assert a.training_part() == b.training_part()
    assert a.training_part() != specs.load(f, "paper", ["learner.gamma=0"]).training_part()


BAD = {
    "unknown key": (GOOD + "learner: {gama: 0.9}\n", "learner.gama", "unknown key"),
    "wrong type": (GOOD + "train: {epochs: many}\n", "train.epochs", "integer"),
    "out of range": (GOOD.replace("size: 5", "size: 2"), "env.size", "greater than or equal to 3"),
    "negative lr": (GOOD + "learner: {lr: -1}\n", "learner.lr", "greater than 0"),
    "too many blocks": (GOOD.replace("blocks: 2", "blocks: 24"), "env", "does not fit"),
    "corner needs two blocks": (GOOD.replace("blocks: 2", "blocks: 1"), "env", "blocks >= 2"),
    "buffer too small": (GOOD + "learner: {buffer_size: 100}\n", "", "cannot hold one epoch"),
    "unreachable entropy": (GOOD + "learner: {target_entropy: 4.83}\n", "", "ln 125 = 4.828 nats"),
    "unknown kind": (GOOD.replace("kind: esr", "kind: magic"), "method", "kind"),
    "missing section": ("name: t\nenv: {kind: gridworld}\nhuman: {kind: noisy_greedy}\n", "method", "missing: this key is required"),
    "duplicate seeds": (GOOD + "train: {seeds: [1, 1]}\n", "train.seeds", "distinct"),
    # the order is part of the run's key and changes no seed's numbers: [1, 0] would be [0, 1] again
    "seeds out of order": (GOOD + "train: {seeds: [3, 0, 1]}\n", "train.seeds", "[3, 0, 1] is not in increasing order: write [0, 1, 3]"),
    "unreadable yaml": ("name: t\nenv: {kind: gridworld\n", "", "unreadable YAML"),
    "not a mapping": ("- 1\n- 2\n", "", "mapping"),
    "unknown budget entry": (GOOD + "budgets: {huge: {train.epochs: 1}}\n", "budgets", "unknown budget"),
    "a paper budget entry": (GOOD + "budgets: {paper: {train.epochs: 1}}\n", "budgets.paper", "the spec as written"),
    "one field set twice by a budget": (GOOD + "budgets: {smoke: {train: {epochs: 1}, train.epochs: 3}}\n", "budgets.smoke",
                                        "train and train.epochs both set train.epochs: keep one"),
    "a section and a key inside it": (GOOD + "budgets: {quick: {train.seeds: 2, train: {seeds: [0, 1]}}}\n",
                                      "budgets.quick", "train.seeds and train both set train.seeds"),
    # a kind starts its section again: every field of it is set, whichever key comes first
    "a kind beside a field of its section": (GOOD + "budgets: {quick: {method.repr_dim: 8, method: {kind: esr}}}\n",
                                             "budgets.quick", "method.repr_dim and method both set method"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_spec_names_key_and_problem(tmp_path, case):
    text, path, problem = BAD[case]
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(specs.SpecError) as e:
        specs.load(f)
    assert e.value.path == path
    assert problem in e.value.problem
    assert str(f) in str(e.value)


def test_an_entropy_target_binds_only_where_a_dual_step_steers_a_policy():
    """ln 6 = 1.792 nats caps an Overcooked robot's entropy; a robot without a learned policy,
    or a learner without dual steps, leaves the target unused."""
    with pytest.raises(specs.SpecError, match="ln 6 = 1.792 nats"):
        specs.load(ROOT / "experiments/cramped_room.yaml", "smoke", ["learner.target_entropy=1.8"])
    assert specs.load(ROOT / "experiments/cramped_room.yaml", "smoke", ["learner.target_entropy=1.79"])
    specs.load(ROOT / "experiments/grid_2_random.yaml", "smoke", ["learner.target_entropy=9"])
    specs.load(ROOT / "experiments/grid_2.yaml", "smoke", ["learner.target_entropy=9", "learner.dual_lr=0"])


def test_a_value_given_for_a_field_the_human_preset_sets_is_refused_not_ignored():
    """The preset replaces the fields it sets, so a --set of one of them would change nothing:
    said before any work, naming the --set; the same value as the preset's, or a field the preset
    leaves alone, is taken."""
    cramped = ROOT / "experiments/cramped_room.yaml"
    with pytest.raises(specs.SpecError) as e:
        specs.load(cramped, "paper", ["human.total_steps=5"])
    assert e.value.source == "--set human.total_steps=5" and e.value.path == "human.total_steps"
    assert "the preset 'paper' sets it to 1000000 on cramped_room, which replaces this value" in e.value.problem
    assert specs.load(cramped, "paper", ["human.total_steps=1000000"]).human.total_steps == 1_000_000
    assert specs.load(cramped, "paper", ["human.lr=0.001"]).human.lr == 0.001
    coord = ROOT / "experiments/coord_ring.yaml"  # a BC clone by the preset: hidden (64, 64), stay_weight 1.0
    with pytest.raises(specs.SpecError, match="human.stay_weight: the preset 'paper' sets it to 1.0 on coord_ring"):
        specs.load(coord, "paper", ["human={stay_weight: 0.5}"])  # a mapping's fields count as theirs
    assert specs.load(coord, "paper", ["human.hidden=[64, 64]"]).human.hidden == (64, 64)  # the preset's own value


def test_missing_file():
    with pytest.raises(specs.SpecError, match="file not found"):
        specs.load("experiments/nope.yaml")


def test_bad_override():
    with pytest.raises(specs.SpecError) as e:
        specs.load("experiments/grid_2.yaml", "paper", ["learner.nope=1"])
    assert e.value.path == "learner.nope"
    with pytest.raises(specs.SpecError, match="key.path=value"):
        specs.load("experiments/grid_2.yaml", "paper", ["learner.gamma"])
    with pytest.raises(specs.SpecError, match="unknown budget"):
        specs.load("experiments/grid_2.yaml", "huge")


@pytest.mark.parametrize("case", ["unknown key", "wrong type", "out of range", "too many blocks", "unreadable yaml"])
def test_cli_exits_2_and_leaves_the_store_alone(tmp_path, capsys, case):
    text, path, problem = BAD[case]
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    store = tmp_path / "store"
    assert main(["--store", str(store), "train", str(f), "--budget", "smoke"]) == 2
    msg = capsys.readouterr().err
    assert str(f) in msg and problem in msg and (path in msg)
    assert not store.exists()


def test_cli_missing_file_and_bad_set(tmp_path, capsys):
    store = tmp_path / "store"
    assert main(["--store", str(store), "train", str(tmp_path / "missing.yaml")]) == 2
    assert "file not found" in capsys.readouterr().err
    assert main(["--store", str(store), "train", "experiments/grid_2.yaml", "--set", "train.epochs=0"]) == 2
    assert "train.epochs" in capsys.readouterr().err
    assert not store.exists()


def test_extends_merges_sections_and_replaces_a_changed_kind(tmp_path):
    (tmp_path / "base.yaml").write_text(GOOD + "learner: {gamma: 0.5, lr: 0.01}\n")
    child = tmp_path / "child.yaml"
    child.write_text("extends: base.yaml\nname: c\nlearner: {gamma: 0.7}\nmethod: {kind: ave, rollout_length: 3}\n")
    spec = specs.load(child)
    assert spec.name == "c"
    assert (spec.learner.gamma, spec.learner.lr) == (0.7, 0.01)  # merged
    assert spec.method.kind == "ave" and spec.method.rollout_length == 3  # replaced, no ESR fields left
    assert spec.env.blocks == 2


def test_a_child_replacing_a_kind_drops_the_base_budgets_entries_for_that_section(tmp_path):
    """The base's budgets were written for its kind (ESR's repr_lr); the child's random robot has
    no such field. The child's own budgets still apply, and the base's for other sections."""
    (tmp_path / "base.yaml").write_text(GOOD + "budgets:\n  quick: {method.repr_lr: 0.001, train.epochs: 7}\n")
    child = tmp_path / "child.yaml"
    child.write_text("extends: base.yaml\nname: c\nmethod: {kind: random}\nbudgets:\n  smoke: {train.epochs: 2}\n")
    assert specs.load(child, "smoke").train.epochs == 2
    quick = specs.load(child, "quick")
    assert quick.method.kind == "random" and quick.train.epochs == 7
    assert specs.load(tmp_path / "base.yaml", "quick").method.repr_lr == 0.001  # the base itself is unchanged


def test_a_bad_budget_entry_from_an_extended_file_names_that_file(tmp_path):
    (tmp_path / "base.yaml").write_text(GOOD + "budgets:\n  quick: {method.repr_lrr: 0.001}\n")
    child = tmp_path / "child.yaml"
    child.write_text("extends: base.yaml\nname: c\n")
    with pytest.raises(specs.SpecError) as e:
        specs.load(child, "smoke")
    assert str(e.value).startswith(f"{tmp_path / 'base.yaml'} (extended by {child}), budgets.quick: method.repr_lrr:")


def test_extends_errors_name_the_key(tmp_path):
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text("extends: b.yaml\n" + GOOD)
    b.write_text("extends: a.yaml\n" + GOOD)
    with pytest.raises(specs.SpecError, match="extends: circular"):
        specs.load(a)
    missing = tmp_path / "m.yaml"
    missing.write_text("extends: nowhere.yaml\n" + GOOD)
    with pytest.raises(specs.SpecError, match="extends: file not found: nowhere.yaml"):
        specs.load(missing)


def test_every_method_has_a_spec_per_paper_gridworld():
    for n in (2, 5, 7, 10):
        for method in ("esr", "random", "ave", "goal_inference", "iq_learn", "oracle"):
            path = Path(f"experiments/grid_{n}.yaml" if method == "esr" else f"experiments/grid_{n}_{method}.yaml")
            spec = specs.load(path)
            assert (spec.method.kind, spec.env.blocks, spec.train.seeds) == (method, n, tuple(range(20)))


def test_quick_budget_warms_up_and_learns_representations_faster():
    quick = specs.load("experiments/grid_2.yaml", "quick")
    assert (quick.train.epochs, quick.learner.warmup_epochs, quick.method.repr_lr) == (150, 20, 1e-3)
    assert specs.load("experiments/grid_2.yaml", "paper").method.repr_lr == 1e-4  # the paper as written
    random_quick = specs.load("experiments/grid_2_random.yaml", "quick")  # no representations: skipped
    assert random_quick.learner.warmup_epochs == 20 and not hasattr(random_quick.method, "repr_lr")


def test_a_human_preset_sets_the_layouts_cloning_fields_and_keys_by_value():
    named = specs.load(Path("experiments/coord_ring_random.yaml"), "quick", ["human.preset=paper_random"])
    assert (named.human.stay_weight, named.human.hidden, named.human.epochs) == (1.0, (64, 64), 60)
    asymm = specs.load(Path("experiments/asymm_advantages.yaml"), "quick", ["human.preset=paper_random"])
    assert (asymm.human.stay_weight, asymm.human.hidden, asymm.human.epochs) == (0.1, (128, 128), 200)
    # the preset replaces the file's own stay_weight: 0.1; written out by hand it is the same run
    by_hand = specs.load(Path("experiments/coord_ring_random.yaml"), "quick", ["human.stay_weight=1.0"])
    assert named.training_part() == by_hand.training_part()
    plain = specs.load(Path("experiments/coord_ring_random.yaml"), "quick")
    assert "preset" not in plain.training_part()["human"]  # runs from before the field keep their keys


def test_the_paper_preset_is_a_whole_human_per_layout_whatever_the_file_s_kind():
    cramped = specs.load(Path("experiments/cramped_room.yaml"), "quick", ["human={preset: paper}"])
    assert cramped.human.kind == "ppo" and (cramped.human.mode, cramped.human.total_steps) == ("shaped", 1_000_000)
    assert cramped.human.random_partner == 0.5
    written_out = specs.load(Path("experiments/cramped_room.yaml"), "quick",
                             ["human={kind: ppo, mode: shaped, total_steps: 1000000, random_partner: 0.5}"])
    assert cramped.training_part() == written_out.training_part()  # keyed by the values, not the name
    ring = specs.load(Path("experiments/coord_ring.yaml"), "quick", ["human={preset: paper}"])
    closest_clone = specs.load(Path("experiments/coord_ring.yaml"), "quick", ["human.preset=paper_random"])
    assert ring.human.kind == "bc" and ring.training_part() == closest_clone.training_part()
    assert specs.load(Path("experiments/coord_ring.yaml"), "quick", ["human={preset: paper, seed: 2}"]).human.seed == 2
    # as a field of a BC section (the smoke budget's clone), a preset that makes another kind is
    # named, not mixed in
    with pytest.raises(specs.SpecError, match=r"human.preset='paper' makes a ppo human on cramped_room, not kind "
                                              r"'bc': give the preset alone, human=\{preset: paper\}"):
        specs.load(Path("experiments/cramped_room.yaml"), "smoke", ["human.preset=paper"])
    with pytest.raises(specs.SpecError, match=r"human.preset='paper' is defined for cramped_room.*not 'forced_coord'"):
        specs.load(Path("experiments/forced_coord_random.yaml"), "quick", ["human={preset: paper}"])
    with pytest.raises(specs.SpecError, match=r"human.preset: 'paper' names an Overcooked layout's human: it needs "
                                              r"env.kind: overcooked"):
        specs.load(Path("experiments/grid_2.yaml"), "paper", ["human={preset: paper}"])


def test_the_paper_layouts_play_with_the_paper_human_except_at_the_smoke_budget():
    """The three paper layouts' specs (every method) name `human: {preset: paper}`; the smoke
    budget, a plumbing check, plays with esr's MLP clone; `human={kind: bc}` is that clone at any
    budget, keyed as the runs made before the switch (their spec wrote it out)."""
    for layout in ("cramped_room", "coord_ring", "asymm_advantages"):
        for method in ("", "_ave", "_iq_learn", "_random"):
            path = Path(f"experiments/{layout}{method}.yaml")
            preset = specs.load(path, "paper", ["human={preset: paper}"]).training_part()
            assert specs.load(path, "paper").training_part() == preset
            assert specs.load(path, "quick").training_part()["human"] == preset["human"]
            smoke = specs.load(path, "smoke")
            assert smoke.human.kind == "bc" and smoke.training_part()["human"] == specs.load(path, "paper", [
                "human={kind: bc, stay_weight: 0.1, epochs: 60, selfplay_episodes: 64}"]).training_part()["human"]
            assert specs.load(path, "smoke", ["human={preset: paper}"]).training_part()["human"] == preset["human"]
    assert specs.load(Path("experiments/cramped_room.yaml")).human.kind == "ppo"
    assert specs.load(Path("experiments/forced_coord.yaml")).human.kind == "bc"  # no preset there


def test_a_human_preset_is_refused_where_it_has_no_settings():
    with pytest.raises(specs.SpecError, match=r"human.preset='paper_random' is defined for cramped_room.*not 'forced_coord'"):
        specs.load(Path("experiments/forced_coord_random.yaml"), "quick", ["human.preset=paper_random"])
    # beside a kind (the smoke budget's clone) the field's own check names it; as the whole
    # section (the file's preset), the preset step does, with the closest name
    with pytest.raises(specs.SpecError, match=r"human.preset: Input should be 'paper_random' or 'paper'"):
        specs.load(Path("experiments/cramped_room.yaml"), "smoke", ["human.preset=closest"])
    with pytest.raises(specs.SpecError, match=r"human.preset: the text 'paper_randm' is not a preset; known: "
                                              r"paper_random, paper; did you mean `paper_random`\?$"):
        specs.load(Path("experiments/cramped_room.yaml"), "quick", ["human.preset=paper_randm"])
    # a preset that is no name at all is one line too, not a crash of the lookup
    for value, described in (("{a: 1}", "a mapping"), ("[1]", "a list"), ("3", "the number 3")):
        with pytest.raises(specs.SpecError, match=rf"human.preset: expected a preset's name \(paper_random, paper\), got {described}$"):
            specs.load(Path("experiments/cramped_room.yaml"), "quick", [f"human.preset={value}"])
    with pytest.raises(specs.SpecError, match=r"human.preset: null is not a preset"):
        specs.load(Path("experiments/cramped_room.yaml"), "quick", ["human.preset=null"])
    # the preset looks its layout up by name: a layout that is no name is one line, wherever it is written
    for key in ("env.layout", "human.layout"):
        with pytest.raises(specs.SpecError, match=rf"{key}: expected a layout's name, got a mapping$"):
            specs.load(Path("experiments/cramped_room.yaml"), "quick", [f"{key}={{k: [0, 1]}}"])


def test_a_bad_value_names_the_set_or_budget_that_gave_it(tmp_path):
    """The user's mistake is where the value came from: a --set, not the spec file (nor the
    file it extends); a spec's own budgets entry; a budget's value quoted by a cross-field rule."""
    with pytest.raises(specs.SpecError) as e:
        specs.load("experiments/grid_5_ave.yaml", "smoke", ["env.size=3", "env.size=0"])
    assert str(e.value) == "--set env.size=0: env.size: Input should be greater than or equal to 3"
    own = tmp_path / "own.yaml"
    own.write_text(f"extends: {Path('experiments/grid_2.yaml').resolve()}\nname: x\n"
                   "budgets: {smoke: {train.epochs: 0}}\n")
    with pytest.raises(specs.SpecError) as e:
        specs.load(own, "smoke")
    assert e.value.source == f"{own}, budgets.smoke" and e.value.path == "train.epochs"
    group = tmp_path / "group.yaml"
    group.write_text(f"extends: {Path('experiments/grid_2.yaml').resolve()}\nname: x\nmethod: {{episode_group: 32}}\n")
    assert specs.load(group, "paper").method.episode_group == 32
    with pytest.raises(specs.SpecError, match=r"batch_size=16: .*\(learner.batch_size from the smoke budget\)"):
        specs.load(group, "smoke")
    with pytest.raises(specs.SpecError, match="a list is set whole"):
        specs.load("experiments/grid_2.yaml", "paper", ["network.conv_channels[0]=8"])


@pytest.mark.parametrize("sets, path, problem", [
    (["train.ep[ochs=1"], "train.ep[ochs", "not a key path"),  # a bracket that is no list index
    (["train.epochs]=1"], "train.epochs]", "not a key path"),
    # a part that is no field name: blamed on the --set as typed, not on the file as an unknown key
    (["train.epochs+=5"], "train.epochs+", "not a key path"),
    (["learner.gamma:=0"], "learner.gamma:", "not a key path"),
    (["train. epochs=5"], "train. epochs", "not a key path"),
    (["train.ep\x1bochs=5"], "train.ep\x1bochs", "not a key path"),
    # a mapping's keys are paths inside its section, named from the section
    (['train={"": 5}'], "train.(an empty key)", "malformed key path"),
    (['train={"a..b": 5}'], "train.a..b", "malformed key path"),
    (['train={"epochs.x": 5}'], "train.epochs", "is not a section"),
])
def test_a_set_key_path_of_no_field_names_is_named_as_written(sets, path, problem):
    with pytest.raises(specs.SpecError) as e:
        specs.load("experiments/grid_2.yaml", "paper", sets)
    assert e.value.source == "--set" and e.value.path == path and problem in str(e.value)


def test_a_set_key_with_a_hyphen_is_an_unknown_key_with_its_suggestion():
    with pytest.raises(specs.SpecError, match=r"^--set method.repr-dim=3: method.repr-dim: unknown key; did you mean `repr_dim`\?$"):
        specs.load("experiments/grid_2.yaml", "paper", ["method.repr-dim=3"])


@pytest.mark.parametrize("key, named", [("ep[ochs", "train.ep[ochs"), ("seeds[0]", "train.seeds[0]"), ("x[y]", "train.x[y]")])
def test_a_file_key_with_a_bracket_is_named_and_not_mistaken_for_a_validator(tmp_path, key, named):
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"extends: {Path('experiments/grid_2.yaml').resolve()}\ntrain: {{'{key}': 5}}\n")
    with pytest.raises(specs.SpecError) as e:
        specs.load(bad, "paper")
    assert e.value.path == named and "unknown key" in str(e.value)


def test_setting_a_kind_starts_that_section_again_as_extends_does():
    """--set method.kind=random on an ESR spec is the Random spec (ESR's fields would be unknown
    keys of the new kind), at every budget; a kind --set leaves unchanged keeps the section."""
    for budget in spec_model.BUDGETS:
        switched = specs.load("experiments/grid_2.yaml", budget, ["method.kind=random"])
        assert switched.training_part() == specs.load("experiments/grid_2_random.yaml", budget).training_part()
    # a spec's own budget entries written for ESR do not apply to the new kind
    assert specs.load("experiments/cramped_room.yaml", "smoke", ["method={kind: random}"]).method.kind == "random"
    ave = specs.load("experiments/grid_2.yaml", "paper", ["method.kind=ave", "method.rollout_length=3"])
    assert (ave.method.kind, ave.method.rollout_length) == ("ave", 3)
    same = specs.load("experiments/grid_2.yaml", "paper", ["method.kind=esr", "method.repr_dim=8"])
    assert same.method.repr_dim == 8 and same.method.repr_lr == specs.load("experiments/grid_2.yaml").method.repr_lr


def test_the_other_problems_are_named_by_place_beside_the_first(tmp_path):
    f = tmp_path / "m.yaml"
    f.write_text(f"extends: {ROOT / 'experiments/grid_2.yaml'}\nmethd: {{}}\ntrain: {{epochs: x, seeds: y}}\n")
    with pytest.raises(specs.SpecError) as e:
        specs.load(f)
    assert e.value.path == "methd"
    assert e.value.problem.endswith("(and 2 more problem(s), at train.epochs, train.seeds)")
    f.write_text("name: m\nenv: {kind: gridworld}\nhuman: {kind: noisy_greedy}\nmethd: {}\n")
    with pytest.raises(specs.SpecError, match=re.escape("(and 1 more problem(s), at method)")):  # the typo's consequence
        specs.load(f)
    many = ", ".join(f"bad{i}: 1" for i in range(5))
    f.write_text(f"name: m\nenv: {{kind: gridworld, {many}}}\nhuman: {{kind: noisy_greedy}}\nmethod: {{kind: random}}\n")
    with pytest.raises(specs.SpecError) as e:
        specs.load(f)
    assert e.value.path == "env.bad0" and e.value.problem.endswith("(and 4 more problem(s), at env.bad1, env.bad2, env.bad3, ...)")


def test_a_misspelt_kind_and_wrong_types_are_named_in_plain_words(tmp_path):
    f = tmp_path / "k.yaml"
    f.write_text("name: y\nenv: {knd: gridworld}\nhuman: {kind: noisy_greedy}\nmethod: {kind: random}\n")
    with pytest.raises(specs.SpecError) as e:
        specs.load(f)
    assert e.value.path == "env.knd" and "did you mean `kind`?" in e.value.problem
    for sets, problem in ((["train.seeds=3.0"], "expected a list of seeds or a count (an integer), got 3.0"),
                          (["name=2024"], "expected text, got the number 2024"),
                          (["name=true"], "expected text, got the boolean true: write it in quotes"),
                          (["train=null"], "train: expected a section (a mapping of keys), got an empty value (null)"),
                          (["train=5"], "train: expected a section (a mapping of keys), got the number 5")):
        with pytest.raises(specs.SpecError, match=re.escape(problem)):
            specs.load("experiments/grid_2.yaml", "paper", sets)
    f.write_text("extends: null\n" + GOOD)
    with pytest.raises(specs.SpecError, match="extends: must be the path of another spec file"):
        specs.load(f)
    f.write_text(f"extends: {tmp_path}\n" + GOOD)
    with pytest.raises(specs.SpecError, match="is not a file"):
        specs.load(f)


def test_a_budget_that_gives_a_section_of_another_kind_keeps_every_field_it_names(tmp_path):
    """A budget entry `human: {kind: bc, stay_weight: 0.5}` on a file whose human is a preset:
    the section starts again from the new kind with all the entry's fields (not the kind alone);
    a --set that chooses the section itself wins over the budget's."""
    text = (ROOT / "experiments/cramped_room.yaml").read_text().replace(
        "smoke: {human: {kind: bc},", "smoke: {human: {kind: bc, stay_weight: 0.5, epochs: 7},")
    assert "stay_weight: 0.5" in text
    path = tmp_path / "spec.yaml"
    path.write_text(text)
    smoke = specs.load(path, "smoke")
    assert (smoke.human.kind, smoke.human.stay_weight, smoke.human.epochs) == ("bc", 0.5, 7)
    assert specs.load(path, "smoke", ["human.seed=3"]).human.seed == 3
    assert specs.load(path, "smoke", ["human={preset: paper}"]).human.kind == "ppo"
    assert specs.load(path, "smoke", ["human={kind: bc}"]).human.stay_weight == 0.1


# Each field that acts only beside another field's value, given away from its default where it
# cannot act: (spec file, the --set values that make it inert, the --set that makes it act).
INERT = [
    ("grid_2", ["method.inferred_codes=16"], "method.human_action=inferred"),
    ("grid_2_goal_inference", ["method.step=0.25"], "method.variant=original"),
    ("cramped_room", ["human.kind=ppo", "human.kl_coef=0.5"], "human.mode=bc_kl"),
    ("cramped_room", ["human.kind=bc", "human.adapt_lr=0.01"], "human.adapt=true"),
    ("cramped_room", ["human.kind=bc", "human.adapt_kl=2.5"], "human.adapt=true"),
    ("cramped_room", ["human.kind=bc", "human.adapt_gamma=0.5"], "human.adapt=true"),
    ("cramped_room_ave", ["method.variant=original", "method.rollout_length=2"], "method.variant=fixed"),
    ("grid_2", ["network.mlp_layers=[8]"], "network.kind=mlp"),
    ("cramped_room", ["network.conv_channels=[8]"], "network.kind=conv"),
    ("cramped_room", ["network.hidden=50"], "network.kind=conv"),
]


def test_every_field_that_acts_only_beside_another_is_covered():
    from esr_cli.common import inert_fields
    covered = {sets[-1].split("=")[0] for _, sets, _ in INERT}
    assert covered == {f"{r.section}.{r.field}" for r in inert_fields.INERT_FIELDS}


@pytest.mark.parametrize("stem, sets, acts", INERT, ids=[s[-1].split("=")[0] for _, s, _ in INERT])
def test_a_field_where_it_cannot_act_is_refused_by_name(stem, sets, acts):
    """It would change only the run's key: a second run of the same program under a new key."""
    path = f"experiments/{stem}.yaml"
    key, value = sets[-1].split("=")
    needs = acts.split("=")[0]
    with pytest.raises(specs.SpecError) as e:
        specs.load(path, "smoke", sets)
    assert e.value.source == f"--set {sets[-1]}" and e.value.path == key
    assert e.value.problem.startswith(f"{value} does nothing while {needs} is ") and f"set {acts.replace('=', ': ')}" in e.value.problem
    specs.load(path, "smoke", [*sets, acts])  # where it acts, it is taken
    specs.load(path, "smoke", [*sets[:-1], f"{key}={_default(key)}"])  # at its default it changes nothing


def test_an_inert_field_in_a_file_names_the_set_that_made_it_inert(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(f"extends: {Path('experiments/grid_2.yaml').resolve()}\nname: x\n"
                 "method: {human_action: inferred, inferred_codes: 16}\n")
    assert specs.load(f, "smoke").method.inferred_codes == 16
    with pytest.raises(specs.SpecError) as e:
        specs.load(f, "smoke", ["method.human_action=observed"])
    assert e.value.source == str(f) and e.value.path == "method.inferred_codes"
    assert "(method.human_action from --set method.human_action=observed)" in e.value.problem


def test_a_spec_written_out_in_full_loads_again(tmp_path):
    """A stored run's spec.yaml holds every field, the inert ones at their defaults."""
    for stem in ("grid_2", "grid_2_goal_inference", "cramped_room"):
        spec = specs.load(f"experiments/{stem}.yaml", "smoke")
        written = yaml.safe_load(specs.to_yaml(spec))
        written.pop("budget")  # chosen with --budget
        f = tmp_path / f"{stem}.yaml"
        f.write_text(yaml.safe_dump(written))
        assert specs.load(f, "smoke") == spec


def _default(key: str) -> str:
    from esr_cli.common import inert_fields
    rule = next(r for r in inert_fields.INERT_FIELDS if f"{r.section}.{r.field}" == key)
    model = next(m for m in spec_model.KIND_MODELS.get(rule.section, {}).values()
                 if rule.field in m.model_fields) if rule.kind else spec_model.NetworkSpec
    return inert_fields.as_yaml(model.model_fields[rule.field].default)


def test_a_conv_bc_human_takes_the_mlp_widths_only_at_their_default():
    """A run's spec.yaml writes every field, `hidden` too; written by hand it must be left out."""
    conv = ["human.kind=bc", "human.network=conv"]
    spec = specs.load("experiments/cramped_room_random.yaml", "smoke", conv)
    written = yaml.safe_load(specs.to_yaml(spec))
    assert written["human"]["hidden"] == [64, 64] and specs.validate(written) == spec
    assert specs.load("experiments/cramped_room_random.yaml", "smoke", [*conv, "human.hidden=[64,64]"]) == spec
    with pytest.raises(specs.SpecError, match="human.hidden sizes the MLP"):
        specs.load("experiments/cramped_room_random.yaml", "smoke", [*conv, "human.hidden=[32]"])


PPO_HUMAN = "human={kind: ppo, total_steps: 2000, num_envs: %d, rollout_steps: %d}"


@pytest.mark.parametrize("envs, steps, path, problem", [
    (1, 9, "human", "1 x 9 x 2 = 18 actor-steps an update, which PPO's 4 minibatches cannot split evenly"),
    (250, 9, "human.total_steps", "2,000 is less than one rollout: num_envs x rollout_steps = 250 x 9 = 2,250"),
])
def test_a_ppo_human_that_ppo_cannot_train_is_refused_before_any_work(tmp_path, capsys, envs, steps, path, problem):
    with pytest.raises(specs.SpecError) as e:
        specs.load("experiments/cramped_room.yaml", "smoke", [PPO_HUMAN % (envs, steps)])
    assert e.value.path == path and problem in e.value.problem
    assert main(["--store", str(tmp_path / "s"), "train", "experiments/cramped_room.yaml", "--budget", "smoke",
                 "--set", PPO_HUMAN % (envs, steps)]) == 2
    assert problem in capsys.readouterr().err and not (tmp_path / "s").exists()
    specs.load("experiments/cramped_room.yaml", "smoke", [PPO_HUMAN % (2, 9)])  # 36 actor-steps split


def test_the_ppo_batch_rule_uses_ppos_own_numbers():
    from esr_cli.common import ppo_batch
    from esr_cli.model.envs.overcooked import Overcooked
    from esr_cli.model.humans import ppo
    assert ppo_batch.MINIBATCHES == ppo.PPOConfig().num_minibatches
    assert ppo_batch.SEATS == ppo.overcooked_env(Overcooked("cramped_room", 400)).players
