"""Store text in a markdown page (esr_cli/common/markdown.py), and what a manifest's sessions say
of where a run was made (esr_cli/storage/provenance.py::origin)."""

from esr_cli.common.markdown import plain_text
from esr_cli.storage import provenance


def test_store_text_in_a_page_opens_no_code_span_link_tag_or_cell():
    hostile = "gpu:X`y` <b>B</b> <!-- esr sweep x --> [l](javascript:alert(1)) a|b \\"
    escaped = plain_text(hostile)
    assert escaped == ("gpu:X\\`y\\` \\<b\\>B\\</b\\> \\<\\!-- esr sweep x --\\> \\[l\\](javascript:alert(1)) a\\|b \\\\")
    # every structural character is preceded by a backslash, and nothing else changes
    assert escaped.replace("\\", "") == hostile.replace("\\", "")
    assert plain_text("gpu:NVIDIA H100 80GB HBM3") == "gpu:NVIDIA H100 80GB HBM3"


def test_a_run_resumed_on_many_devices_names_a_few_and_counts_the_rest():
    sessions = [{"commit": "3a61962", "device": f"gpu:card {i}", "dirty": "false"} for i in range(3800)]
    made = provenance.origin({"sessions": sessions})
    assert made.device == "gpu:card 0, then gpu:card 1, then gpu:card 2, then 3797 more"
    assert made.modified is False  # only `true` says the checkout had edits; a text is not one
    assert provenance.origin({"sessions": [{"commit": "3a61962", "dirty": True}]}).modified is True
