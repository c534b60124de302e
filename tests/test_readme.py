"""The README read top to bottom by a new user: the CPU-only note comes before the install
command, the test suite's duration is stated, and no command names a module that an install
does not provide."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_cpu_build_is_installed_before_the_package():
    text = (ROOT / "README.md").read_text()
    setup = text[text.index("## Set-up"):text.index("## Quickstart")]
    cpu = setup.index("download.pytorch.org/whl/cpu")
    install = setup.index('pip install -e ".[dev]"')
    assert cpu < install, "the CPU-build note must come before the install command"
    assert len(re.findall(r"^```bash$", setup, re.M)) == 2  # the two set-up commands
    assert re.search(r"about \d+ minutes on 2 cores", setup), "state the test suite's duration"


def test_no_page_tells_users_to_run_the_removed_training_module():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    bad = [p.name for p in pages if "python -m training" in p.read_text()
           or "-m training.tune" in p.read_text()]
    assert bad == []


def test_a_torch_without_custom_op_is_refused_at_import_naming_the_version():
    import subprocess
    import sys

    code = ("import torch; del torch.library.custom_op\n"
            "try:\n    import diffsmf\nexcept ImportError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120).stdout
    assert "diffsmf needs torch >= 2.4" in out and "this is torch" in out
