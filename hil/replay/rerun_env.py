"""Import Rerun with its usage analytics turned off, for every process the project starts.

Rerun 0.41 (crate ``re_analytics``, ``native/pipeline.rs``) starts its analytics pipeline unless
its config file ``$XDG_CONFIG_HOME/rerun/analytics.json`` (default ``~/.config/rerun``) says
``"analytics_enabled": false`` — what ``rerun analytics disable`` writes — or the variable ``CI`` is
set; ``FORCE_RERUN_ANALYTICS`` forces it on whatever the file says. There is no other switch.
:func:`disable_rerun_analytics` therefore, before Rerun is imported: removes
``FORCE_RERUN_ANALYTICS`` from the environment (of this process and so of its children) and
writes that config file with ``analytics_enabled`` false when it is missing or says otherwise
(keeping its other fields). It never sets ``CI`` (other tools read it).

:func:`import_rerun` also quiets one line: the live stream writes its ``.rrd`` without a footer on
purpose (:mod:`hil.replay.live`: the footer's manifest grows without bound in memory), and Rerun's
file sink warns about that on the terminal each time. Before Rerun is first imported, its Rust log
filter (``RUST_LOG``, read at import) gets ``re_log_encoding::rrd::file_sink=error`` added (with
``warn`` for everything else when ``RUST_LOG`` was unset): that module's errors still show.
"""

from __future__ import annotations

import json
import os
import sys
import uuid
from pathlib import Path
from types import ModuleType
from typing import Any

from hil.errors import HilError
from hil.log import get_logger

_log = get_logger(__name__)

#: The variable that forces Rerun's analytics on (removed from the environment).
FORCE_ANALYTICS_ENV = "FORCE_RERUN_ANALYTICS"
#: Rerun's Rust log filter, and what :func:`import_rerun` adds to it (module doc).
RUST_LOG_ENV = "RUST_LOG"
QUIET_FILE_SINK = "re_log_encoding::rrd::file_sink=error"
#: Log event: the Rerun analytics config was written (off).
EV_ANALYTICS_DISABLED = "rerun_analytics_disabled"


class ViewerUnavailableError(HilError):
    """The ``viewer`` extra (rerun-sdk) is not installed, or its analytics cannot be turned off."""


def _xdg_dir(var: str, default: str) -> Path:
    value = os.environ.get(var, "")
    return Path(value) if value and Path(value).is_absolute() else Path.home() / default


def analytics_config_path() -> Path:
    """Where Rerun reads its analytics switch: ``$XDG_CONFIG_HOME/rerun/analytics.json``."""
    return _xdg_dir("XDG_CONFIG_HOME", ".config") / "rerun" / "analytics.json"


def disable_rerun_analytics() -> Path:
    """Turn Rerun's analytics off (module doc) and return the config file that says so.

    Idempotent: a file already saying ``analytics_enabled: false`` is left as it is.

    Raises:
        ViewerUnavailableError: the config file cannot be written (analytics would stay on).
    """
    os.environ.pop(FORCE_ANALYTICS_ENV, None)
    path = analytics_config_path()
    doc: dict[str, Any] = {}
    try:
        loaded = json.loads(path.read_text(encoding="utf-8"))
        if isinstance(loaded, dict):
            doc = loaded
    except (OSError, ValueError):
        doc = {}
    if doc.get("analytics_enabled") is False:
        return path
    data_dir = _xdg_dir("XDG_DATA_HOME", ".local/share") / "rerun" / "analytics"
    doc = {"analytics_id": uuid.uuid4().hex, "metadata": {}, **doc, "analytics_enabled": False,
           "config_file_path": str(path), "data_dir_path": str(doc.get("data_dir_path", data_dir))}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(doc), encoding="utf-8")
        tmp.replace(path)
    except OSError as exc:
        raise ViewerUnavailableError(f"{path}: cannot turn Rerun's usage analytics off: "
                                     f"{exc.strerror or exc}") from None
    _log.info(EV_ANALYTICS_DISABLED, path=str(path))
    return path


def quiet_file_sink_warning() -> str:
    """Add :data:`QUIET_FILE_SINK` to ``RUST_LOG`` (module doc); the new value. Idempotent."""
    current = os.environ.get(RUST_LOG_ENV, "").strip()
    if QUIET_FILE_SINK not in current.split(","):
        os.environ[RUST_LOG_ENV] = f"{current or 'warn'},{QUIET_FILE_SINK}"
    return os.environ[RUST_LOG_ENV]


def import_rerun() -> ModuleType:
    """``rerun``, imported after :func:`disable_rerun_analytics`.

    Raises:
        ViewerUnavailableError: rerun-sdk is not installed, or analytics cannot be turned off.
    """
    disable_rerun_analytics()
    if "rerun" not in sys.modules:
        quiet_file_sink_warning()
    try:
        import rerun
    except ImportError as exc:
        raise ViewerUnavailableError("the 3D viewer needs rerun-sdk "
                                     f"(pip install 'needle-guide-hil[viewer]'): {exc}") from None
    return rerun
