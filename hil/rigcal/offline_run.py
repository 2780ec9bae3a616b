"""``hil rig-calibrate --samples FILE``: read, align, solve, summarise and (optionally) write the
hand-eye result file (docs/rig-calibration.md, "Offline, from recorded samples").

The result file is ``hil.hand_eye`` version 1 (the rig calibration file's ``hand_eye`` part needs
the flange-marker layout, which recorded pose pairs do not give), a JSON object::

    {"schema": "hil.hand_eye", "version": 1,
     "units": {"length": "mm", "angle": "deg", "time": "ms"}, "created_utc": "...",
     "samples": FILE, "format": ..., "setup": "eye-to-hand" | "eye-in-hand",
     "convention": "...", ... every field of the --json summary (X, Z, residuals, methods, ...)}

Nothing is written unless the whole solve succeeded.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any, TextIO

from hil.log import get_logger
from hil.rigcal.offline import OfflineResult, solve_offline
from hil.rigcal.rigfile import save_rig_calibration
from hil.rigcal.sample_readers import detect_format, read_samples
from hil.rigcal.samples import PosePairs, SamplesError
from hil.rigcal.streams import align_streams

_log = get_logger(__name__)
EV_OFFLINE_DONE = "rigcal_offline_done"
SCHEMA = "hil.hand_eye"
VERSION = 1
CONVENTIONS = {
    "eye-to-hand": "T_camera_from_target = Z @ T_base_from_flange @ X, X = T_flange_from_target, "
                   "Z = T_camera_from_base",
    "eye-in-hand": "T_base_from_target = T_base_from_flange @ X @ T_camera_from_target, "
                   "X = T_flange_from_camera, Z = T_base_from_target",
}


def _matrix(M: Any) -> list[list[float]]:
    return [[float(v) for v in row] for row in M]


def summary(result: OfflineResult, fmt: str, time_offset: dict[str, float] | None) -> dict[str, Any]:
    """The ``--json`` object (docs/rig-calibration.md lists every field)."""
    s: dict[str, Any] = {
        "setup": result.setup, "format": fmt, "convention": CONVENTIONS[result.setup],
        "pairs": result.pairs, "pairs_used": result.pairs_used, "outliers": result.outliers,
        "X": _matrix(result.X), "Z": _matrix(result.Z),
        "residual_mm_rms": result.residual_mm_rms, "residual_deg_rms": result.residual_deg_rms,
        "validation": result.validation, "start": result.start, "methods": result.methods,
        "solve_s": result.solve_s,
        "per_pair": [{"where": p.where, "error_mm": p.error_mm, "error_deg": p.error_deg, "role": p.role}
                     for p in result.per_pair],
    }
    if time_offset is not None:
        s["time_offset_ms"] = time_offset["offset_ms"]
        s["time_offset_sigma_ms"] = time_offset["sigma_ms"]
        s["time_offset_correlation"] = time_offset["correlation"]
    return s


def run_offline(path: Path, fmt: str | None, setup: str | None, out: Path | None) -> dict[str, Any]:
    """Solve from a samples file; write ``out`` (when given) only after everything succeeded.
    ``setup`` None: eye-in-hand for the ``eth`` format, else eye-to-hand.

    Raises:
        SamplesError: every problem with the file (one line naming file, line or pair, problem).
        InputFileError: ``out`` cannot be written.
    """
    if not path.is_file():
        raise SamplesError(str(path), "no such file")
    fmt = fmt or detect_format(path)
    setup = setup or ("eye-in-hand" if fmt == "eth" else "eye-to-hand")
    data = read_samples(path, fmt, setup == "eye-in-hand")
    offset: dict[str, float] | None = None
    if isinstance(data, PosePairs):
        pairs = data
    else:
        aligned = align_streams(data, str(path))
        pairs = aligned.pairs
        offset = {"offset_ms": aligned.time_offset_ms, "sigma_ms": aligned.delay.sigma_ms,
                  "correlation": aligned.delay.correlation}
    result = solve_offline(pairs, setup, str(path))
    s = summary(result, fmt, offset)
    _log.info(EV_OFFLINE_DONE, samples=str(path), setup=setup, pairs=result.pairs,
              pairs_used=result.pairs_used, residual_mm_rms=round(result.residual_mm_rms, 4),
              residual_deg_rms=round(result.residual_deg_rms, 4), solve_s=round(result.solve_s, 4))
    if out is not None:
        created = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        doc = {"schema": SCHEMA, "version": VERSION, "units": {"length": "mm", "angle": "deg", "time": "ms"},
               "created_utc": created, "samples": str(path), **s}
        save_rig_calibration(doc, out)
        s["hand_eye_file"] = str(out)
    return s


def print_offline_text(s: dict[str, Any], out: TextIO) -> None:
    """The human-readable summary."""
    out.write(f"setup            {s['setup']} ({s['convention']})\n")
    if "time_offset_ms" in s:
        out.write(f"time offset      {s['time_offset_ms']:.1f} ms +- {s['time_offset_sigma_ms']:.1f} ms "
                  f"(camera stamp - robot stamp; correlation {s['time_offset_correlation']:.2f})\n")
    out.write(f"pairs            {s['pairs']} ({s['pairs_used']} fitted, outliers "
              f"{', '.join(s['outliers']) or 'none'})\n")
    out.write(f"residual         {s['residual_mm_rms']:.3f} mm RMS, {s['residual_deg_rms']:.3f} deg RMS\n")
    v = s["validation"]
    if v["pairs"]:
        out.write(f"validation       {v['residual_mm_rms']:.3f} mm RMS, {v['residual_deg_rms']:.3f} deg RMS "
                  f"on {v['pairs']} held-out pairs\n")
    for name, X in (("X", s["X"]), ("Z", s["Z"])):
        for i, row in enumerate(X[:3]):
            label = f"{name} (mm)" if i == 0 else ""
            out.write(f"{label:<17}" + " ".join(f"{x:10.4f}" for x in row) + "\n")
    out.write(f"methods          X against the refined one (start: {s['start']})\n")
    for m, d in s["methods"].items():
        if "failed" in d:
            out.write(f"  {m:<11} failed: {d['failed']}\n")
        else:
            out.write(f"  {m:<11} {d['dt_mm']:8.3f} mm  {d['dr_deg']:7.3f} deg\n")
    out.write(f"solve            {s['solve_s']:.3f} s\n")
    if "hand_eye_file" in s:
        out.write(f"hand-eye file    {s['hand_eye_file']}\n")
