"""Every step of the user guide (docs/guide/*.md) runs as written.

In each page, in order:

* a ```python block with ``title="NAME"`` is written to the file NAME (the page asks the reader
  to save it), any other ```python block is executed, in one namespace per page;
* a ```bash block is run line by line: each command must be ``diffsmf ...`` (run in-process
  through `diffsmf.cli.main`) and must exit with status 0;
* ```text / ```shell blocks are shown, not run (program output, installation).

Each page runs in its own temporary folder, so files written by one block are read by the next.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide"
FENCE = re.compile(r"^```(\w+)([^\n]*)\n(.*?)^```\s*$", re.M | re.S)
QUIET = ("filter", "audit", "tune", "design-observer")  # commands run with --quiet in the test
PAGES = sorted(p.name for p in GUIDE.glob("*.md") if p.name != "index.md")


def blocks(text: str) -> list[tuple[str, str, str]]:
    """``(language, fence attributes, code)`` of every fenced block of a page."""
    return [(m.group(1), m.group(2), m.group(3)) for m in FENCE.finditer(text)]


def _commands(code: str) -> list[str]:
    joined = code.replace("\\\n", " ")
    return [ln.strip() for ln in joined.splitlines() if ln.strip() and not ln.startswith("#")]


def test_guide_pages_exist():
    assert {"own_system.md", "filter_data.md", "tune.md", "pwl.md", "observer.md"} <= set(PAGES)


SLOW_PAGES = {"filter_data.md", "observer.md"}  # 7-11 s each: deselected by -m "not slow"


@pytest.mark.parametrize(
    "page", [pytest.param(p, marks=pytest.mark.slow) if p in SLOW_PAGES else p for p in PAGES]
)
def test_guide_page_runs(page, tmp_path, monkeypatch):
    from diffsmf.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    text = (GUIDE / page).read_text()
    ns: dict = {"__name__": f"guide_{page[:-3]}"}
    before = set(sys.modules)
    ran = 0
    try:
        for i, (lang, attrs, code) in enumerate(blocks(text)):
            where = f"{page} block {i + 1}"
            if lang == "python":
                title = re.search(r'title="([^"]+)"', attrs)
                if title:
                    Path(title.group(1)).write_text(code)
                    continue
                exec(compile(code, where, "exec"), ns)  # noqa: S102 - the guide's own code
                ran += 1
            elif lang == "bash":
                for cmd in _commands(code):
                    argv = shlex.split(cmd)
                    assert argv[0] == "diffsmf", f"{where}: only diffsmf commands run: {cmd}"
                    quiet = ["--quiet"] if argv[1] in QUIET else []
                    rc = main([*argv[1:], *quiet])
                    assert rc == 0, f"{where}: {cmd} exited with {rc}"
                    ran += 1
    finally:  # forget the modules this page imported from its folder (my_model, ...)
        for name in set(sys.modules) - before:
            if str(tmp_path) in str(getattr(sys.modules[name], "__file__", "") or ""):
                del sys.modules[name]
    assert ran > 0, f"{page}: nothing was run"
