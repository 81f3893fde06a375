"""Where the committed products live (the repository checkout)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["repo_root", "default_library_path"]


def repo_root() -> Path:
    """The checkout holding ``library/``, ``layouts/``, ``sensing/`` (editable install)."""
    return Path(__file__).resolve().parents[1]


def default_library_path() -> Path:
    return repo_root() / "library" / "paper.npz"
