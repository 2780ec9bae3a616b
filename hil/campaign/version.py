"""What a campaign run is a function of, besides its scenario and seed: the code version and the
config digest. Both are recorded in every run's record and in the summary, checked on each worker
before a run, and compared by ``hil campaign merge`` (docs/campaign.md, "Records").

The code version is the git commit of the checkout the ``hil`` package is imported from, with
whether the tracked files differ from it (and a digest of that difference), when git and the
checkout are there; else the installed package version. ``source`` says which.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hil import __version__
from hil.session.log import file_sha256

#: The checkout the package is imported from (an editable install or a source tree).
PACKAGE_ROOT = Path(__file__).resolve().parents[2]
#: Bound of one git call (s).
GIT_TIMEOUT_S = 20.0


def _git(root: Path, *args: str) -> bytes:
    out = subprocess.run(
        ["git", "-C", str(root), *args], check=True, capture_output=True, timeout=GIT_TIMEOUT_S
    )
    return out.stdout


def code_version(root: Path | None = None) -> dict[str, Any]:
    """The code version of the checkout at ``root`` (default: the one this package comes from).

    Returns ``{"id", "source": "git", "commit", "dirty", "diff_sha256", "package"}`` when ``root``
    is a git checkout and git runs (``dirty``: tracked files differ from the commit, untracked files
    not counted; ``diff_sha256``: SHA-256 of ``git diff HEAD``, None when clean), else
    ``{"id", "source": "package", "package"}``. ``id`` is the one string compared between workers
    and shards: ``git:<commit>``, ``git:<commit>+dirty.<first 12 hex of diff_sha256>`` or
    ``package:<version>``. Not cached: a worker checks it before every run, as every run's process
    imports the checkout afresh (an edit during a campaign shows). Blocking (two or three git
    calls, ~15 ms); never raises.
    """
    root = root or PACKAGE_ROOT
    if (root / ".git").exists() and shutil.which("git") is not None:
        try:
            commit = _git(root, "rev-parse", "HEAD").decode().strip()
            dirty = bool(_git(root, "status", "--porcelain", "--untracked-files=no").strip())
            diff = hashlib.sha256(_git(root, "diff", "HEAD", "--binary")).hexdigest() if dirty else None
        except (OSError, subprocess.SubprocessError):
            pass
        else:
            ident = f"git:{commit}" + (f"+dirty.{diff[:12]}" if diff else "")
            return {"id": ident, "source": "git", "commit": commit, "dirty": dirty, "diff_sha256": diff,
                    "package": __version__}
    return {"id": f"package:{__version__}", "source": "package", "package": __version__}


def config_digest(paths: Sequence[str | Path]) -> str:
    """SHA-256 (hex) over the contents of ``paths`` in order (the setup TOML, then the plan JSON):
    the same files at other paths (another machine's checkout) give the same digest.

    Raises:
        OSError: a file cannot be read.
    """
    h = hashlib.sha256()
    for p in paths:
        h.update(file_sha256(p).encode())
    return h.hexdigest()
