"""A run's checkpoint files (esr_cli/storage/checkpoint_files.py): which steps are intact."""

from esr_cli.storage import checkpoint_files as cf


def test_a_checkpoint_whose_metadata_is_larger_than_esr_writes_is_not_intact(tmp_path):
    """orbax parses a checkpoint's metadata files whole: one of more than 16 MiB (digests recorded
    to match, as a forged archive would) makes the step not intact, so nothing resumes from it or
    imports it; array data of any size under a `d/` folder is a checkpoint's own."""
    step = tmp_path / cf.CHECKPOINT_DIR / "2" / "default"
    (step / "d").mkdir(parents=True)
    (step / "_METADATA").write_text("{}")
    with open(step / "d" / "0123", "wb") as f:
        f.truncate(cf.MAX_METADATA_BYTES + 1)  # sparse: big arrays are fine
    cf.record_digests(tmp_path, [2], 2)
    assert cf.verified_steps(tmp_path) == [2]
    with open(step / "_METADATA", "wb") as f:
        f.truncate(cf.MAX_METADATA_BYTES + 1)
    cf.record_digests(tmp_path, [2], 2)  # digests that match
    assert cf.verified_steps(tmp_path) == []


def test_an_epochs_problem_names_only_what_disagrees_with_the_folder(tmp_path):
    """The folder's epoch against the state's, the metrics' and the run's length: a fact that
    agrees with the folder is not named as if it were the problem."""
    (tmp_path / "metrics.jsonl").write_text("".join(f'{{"epoch": {e}, "env_steps": 1, "return": [0.0]}}\n' for e in (1, 2)))
    assert cf.epochs_problem(tmp_path, 2, 4, [2]) is None
    assert cf.epochs_problem(tmp_path, 4, 4, [4]) == "checkpoint folder says epoch 4 but metrics end at 2"
    assert cf.epochs_problem(tmp_path, 2, 4, [1]) == "checkpoint folder says epoch 2 but its state holds epoch 1"
    assert cf.epochs_problem(tmp_path, 4, 4, [1, 3]) == "checkpoint folder says epoch 4 but its state holds epochs 1, 3 and metrics end at 2"
    assert cf.epochs_problem(tmp_path, 2, 1, [2]) == "checkpoint folder says epoch 2 in a run of 1 epochs"
    assert cf.epochs_problem(tmp_path, 9, 4, None) == "checkpoint folder says epoch 9 but metrics end at 2, in a run of 4 epochs"


def test_a_state_that_holds_no_epoch_is_named_not_a_crash(tmp_path):
    (tmp_path / "metrics.jsonl").write_text('{"epoch": 1, "env_steps": 1, "return": [0.0]}\n')
    assert cf.epochs_problem(tmp_path, 1, 4, []) == "checkpoint folder says epoch 1 but its state holds no epoch"
