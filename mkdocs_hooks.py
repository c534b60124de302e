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


#: The marker on docs/writing_models.md replaced by the table of supported operations.
OPS_MARKER = "<!-- supported-ops -->"


def ops_table() -> str:
    """Markdown table of the engine's rule registry, by category (cannot drift from the code)."""
    import diffsmf.interval.capture  # noqa: F401 - registers the extension rule
    from diffsmf.interval.rules import supported_ops

    lines = ["| category | ATen operations with an inclusion rule |", "|---|---|"]
    for cat, ops in supported_ops().items():
        lines.append(f"| {cat} | " + ", ".join(f"`{o}`" for o in ops) + " |")
    return "\n".join(lines)


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    """Fill the supported-operations table of the "Writing models" page from the registry."""
    if OPS_MARKER in markdown:
        return markdown.replace(OPS_MARKER, ops_table())
    return markdown
