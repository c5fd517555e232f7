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
