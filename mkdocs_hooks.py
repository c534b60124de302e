"""mkdocs hook (local, no plugin to install): every ``docs/*.md`` page gets a nav entry.

Pages listed in ``mkdocs.yml`` keep their place and title; a page added to ``docs/`` later and
not yet listed is appended to the "Chapters" section under the title of its first ``# ``
heading, so a new chapter is never built but unreachable.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


def _listed(nav: Any) -> set[str]:
    """Every page path in a nav tree."""
    out: set[str] = set()
    if isinstance(nav, str):
        out.add(nav)
    elif isinstance(nav, list):
        for item in nav:
            out |= _listed(item)
    elif isinstance(nav, dict):
        for value in nav.values():
            out |= _listed(value)
    return out


def _title(path: Path) -> str:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    return path.stem.replace("_", " ").capitalize()


def on_config(config: Any, **kwargs: Any) -> Any:
    """Append the unlisted top-level pages of ``docs/`` to the "Chapters" section."""
    nav = config.get("nav")
    if not nav:
        return config
    listed = _listed(nav)
    missing = sorted(
        p for p in Path(config["docs_dir"]).glob("*.md") if p.name not in listed
    )
    if not missing:
        return config
    chapters = next((item["Chapters"] for item in nav
                     if isinstance(item, dict) and "Chapters" in item), None)
    if chapters is None:
        chapters = []
        nav.append({"Chapters": chapters})
    for p in missing:
        chapters.append({_title(p): p.name})
    return config
