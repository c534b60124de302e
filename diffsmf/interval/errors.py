"""The engine's error type."""

from __future__ import annotations

__all__ = ["EngineError"]


class EngineError(NotImplementedError, ValueError):
    """A model uses something the guarantee engine cannot enclose (a ``ValueError``: the CLI
    prints one line)."""
