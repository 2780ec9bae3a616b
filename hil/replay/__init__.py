"""3D replay and live view of procedures in the Rerun viewer (docs/replay.md).

:func:`write_replay` turns a verified session log into one ``.rrd`` recording on the session's
own clock; :class:`~hil.replay.live.LiveViewerPlugin` streams a run as it happens (a runtime
plugin on the snapshot hooks). Needs the ``viewer`` extra (``rerun-sdk``); usage analytics of
Rerun are turned off before it is imported (:mod:`hil.replay.rerun_env`).
"""

from hil.replay.recording import ReplayError, ReplayResult, write_replay

__all__ = ["ReplayError", "ReplayResult", "write_replay"]
