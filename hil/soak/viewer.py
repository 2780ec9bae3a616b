"""The live viewer attached to a soak (``hil soak --viewer FILE.rrd|ADDRESS``): the run's plugin
manager with the live Rerun stream (:mod:`hil.replay.live`) on the snapshot hooks, the truth
meter's positions streamed too, and the stream's cost for the soak's JSON (``viewer``).

The cost is what the plugin adds to a supervisor tick: its hook's time per call (it runs in the
controller's thread after every tick, and after every transition), measured around the hook's
body (``LiveViewerPlugin.hook_cost``, ``time.perf_counter_ns``, every call in 1 µs bins), p50 /
p99 / max in ms (a percentile is its bin's upper edge, the maximum exact). The worker
thread that writes through Rerun runs beside the supervisor; what it costs the servo loop shows
in the soak's servo figures, to be compared with a soak without ``--viewer``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hil.config.build import Devices
    from hil.controller.controller import Controller
    from hil.replay.live import LiveViewerPlugin
    from plugins.manager import HilPlugins


def check_viewer_target(target: str | None) -> None:
    """Refuse a bad ``--viewer`` before the soak starts anything: a file in a directory that does
    not exist, or no rerun-sdk.

    Raises:
        InputFileError: ``target`` is a file whose directory does not exist.
        ViewerUnavailableError: rerun-sdk is missing.
    """
    if target is None:
        return
    from hil.replay.live import check_target
    from hil.replay.rerun_env import import_rerun

    check_target(target)
    import_rerun()


def open_soak_viewer(target: str) -> tuple[LiveViewerPlugin, HilPlugins]:
    """The live stream to ``target`` (its worker thread runs: :func:`close_soak_viewer` it on
    every path) and a plugin manager holding it and no installed plugin (entry points are not
    loaded: the soak measures this stream's cost alone).

    Raises:
        InputFileError: ``target`` is a file whose directory does not exist.
        ViewerUnavailableError: rerun-sdk is missing.
    """
    from hil.replay.live import PLUGIN_NAME, open_live_viewer
    from plugins.manager import HilPlugins

    live = open_live_viewer(target)
    try:
        hooks = HilPlugins(load_entry_points=False)
        hooks.register(live, PLUGIN_NAME)
    except BaseException:
        live.close()
        raise
    return live, hooks


def open_devices_and_viewer(devices: Devices, viewer: str | None,
                            ) -> tuple[LiveViewerPlugin | None, HilPlugins | None]:
    """Open the live stream to ``viewer`` (when given: :func:`open_soak_viewer`), then the
    devices; the stream is closed again when they fail to open. ``(None, None)`` without one."""
    live, hooks = (None, None) if viewer is None else open_soak_viewer(viewer)
    try:
        devices.open_all()
    except BaseException:
        close_soak_viewer(live)
        raise
    return live, hooks


def follow_truth(live: LiveViewerPlugin | None, ctl: Controller) -> None:
    """Stream the simulator's true positions the controller's truth meter writes (one attribute
    read in the hook); nothing without a stream."""
    if live is None:
        return
    meter = ctl.truth_meter
    live.follow_truth(lambda: meter.last_positions)


def close_soak_viewer(live: LiveViewerPlugin | None) -> dict[str, Any]:
    """Close the stream (idempotent) and return its figures: the counts of
    ``LiveViewerPlugin.counts``, ``truth_written``, ``hook_calls`` and ``hook_ms`` (p50 / p99 /
    max of the hook's time per call, ms; module doc). Empty without a stream."""
    if live is None:
        return {}
    counts = live.close()
    fig = live.hook_cost.figures()

    def ms(us: float | None) -> float | None:
        return None if us is None else round(us / 1e3, 6)

    hook_ms = {"p50": ms(fig.p50_us), "p99": ms(fig.p99_us), "max": ms(fig.max_us)}
    return {**counts, "truth_written": live.truth_written, "hook_calls": fig.count, "hook_ms": hook_ms}
