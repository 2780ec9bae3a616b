"""Where the tests find the real recorded data (never committed into this repository).

``../shared/data`` beside the repository root (CI has ``shared/`` beside the clone); the
environment variable ``HIL_SHARED_DATA`` points elsewhere (a worktree whose parent has no
``shared/``). A missing path FAILS the test naming it: it never skips.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path:
    """The shared data directory (HIL_SHARED_DATA, else <repo root>/../shared/data)."""
    env = os.environ.get("HIL_SHARED_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """``shared_data_dir() / parts``; fails the calling test naming the path when it is absent."""
    path = shared_data_dir().joinpath(*parts)
    if not path.exists():
        pytest.fail(f"shared data missing: {path} (put ../shared/data beside the repository or set "
                    "HIL_SHARED_DATA)")
    return path
