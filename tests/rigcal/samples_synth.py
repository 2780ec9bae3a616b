"""Synthetic hand-eye pose pairs with a known X and Z (conventions of hil.rigcal.offline), and
writers of the sample formats, for the tests of ``hil rig-calibrate --samples``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from hil.rigcal.samples import inverse, transform

FloatArray = NDArray[np.float64]


def random_pose(rng: np.random.Generator, t_scale_mm: float) -> FloatArray:
    return transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * t_scale_mm)


def synth_pairs(rng: np.random.Generator, n: int, eye_in_hand: bool, noise_mm: float = 0.0,
                noise_deg: float = 0.0) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``(X, Z, B, C)`` (mm): robot poses ``B`` tilted by ~0.4 rad about random axes around
    (400, 0, 300) mm, camera poses ``C`` from the model, perturbed on the target side by
    Gaussian noise of ``noise_mm`` per axis and ``noise_deg`` per axis."""
    X, Z = random_pose(rng, 50.0), random_pose(rng, 500.0)
    B = np.array([transform(Rotation.from_rotvec(rng.normal(size=3) * 0.4).as_matrix(),
                            rng.normal(size=3) * 100.0 + [400.0, 0.0, 300.0]) for _ in range(n)])
    C = inverse(B @ X) @ Z if eye_in_hand else Z @ B @ X
    for k in range(n):
        N = transform(Rotation.from_rotvec(np.radians(rng.normal(size=3) * noise_deg)).as_matrix(),
                      rng.normal(size=3) * noise_mm)
        C[k] = C[k] @ N
    return X, Z, B, C


def quat_xyzw(T: FloatArray) -> list[float]:
    return [float(v) for v in Rotation.from_matrix(T[:3, :3]).as_quat()]   # scipy: scalar last


def write_csv_pairs(path: Path, B: FloatArray, C: FloatArray, scale: float = 1e-3,
                    layout: str = "quat") -> None:
    """Our CSV, one pair a row (translations times ``scale``: 1e-3 writes metres)."""
    if layout == "quat":
        cols = ["t"] + [f"{s}_{c}" for s in ("robot", "camera")
                        for c in ("x", "y", "z", "qx", "qy", "qz", "qw")]
    else:
        cols = ["t"] + [f"{s}_m{r}{c}" for s in ("robot", "camera") for r in range(4) for c in range(4)]
    lines = ["# robot = T_base_from_flange, camera = T_camera_from_target", ",".join(cols)]
    for k in range(len(B)):
        cells = [f"{0.1 * k:.3f}"]
        for T in (B[k], C[k]):
            M = T.copy()
            M[:3, 3] *= scale
            if layout == "quat":
                cells += [repr(float(v)) for v in M[:3, 3]] + [repr(v) for v in quat_xyzw(M)]
            else:
                cells += [repr(float(v)) for v in M.ravel()]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def write_opencv_yaml(path: Path, B: FloatArray, C: FloatArray, count: int | None = None) -> None:
    """OpenCV FileStorage, metres, T1_i/T2_i numbered from 0."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("frameCount", len(B) if count is None else count)
    for k in range(len(B)):
        for key, T in (("T1", B[k]), ("T2", C[k])):
            M = T.copy()
            M[:3, 3] *= 1e-3
            fs.write(f"{key}_{k}", M)
    fs.release()


def easy_handeye_text(B: FloatArray, C: FloatArray, eye_in_hand: bool) -> str:
    """easy_handeye(2) saved samples (metres); ``robot`` is T_effector_from_base for eye-on-base."""
    R = B if eye_in_hand else inverse(B)
    ctype = "eye_in_hand" if eye_in_hand else "eye_on_base"
    out = [f"parameters:\n  name: test\n  calibration_type: {ctype}\nsamples:"]
    for k in range(len(B)):
        for i, (key, T) in enumerate((("robot", R[k]), ("tracking", C[k]))):
            t = T[:3, 3] * 1e-3
            q = quat_xyzw(T)
            out.append(f"{'- ' if i == 0 else '  '}{key}:\n    translation:\n"
                       + "".join(f"      {a}: {v!r}\n" for a, v in zip("xyz", t.tolist(), strict=True))
                       + "    rotation:\n"
                       + "".join(f"      {a}: {v!r}\n" for a, v in zip("xyzw", q, strict=True)))
    return "\n".join(out).replace("\n\n", "\n") + "\n"


def shared_data_dir() -> Path:
    """``<repository root>/../shared/data``. The repository root is the main checkout's: in a git
    worktree (``.git`` is a file naming its git dir) the root of the checkout that owns it."""
    repo = Path(__file__).resolve().parents[2]
    git = repo / ".git"
    if git.is_file():
        gitdir = (repo / git.read_text().split(":", 1)[1].strip()).resolve()
        common = gitdir / "commondir"
        if common.is_file():
            repo = (gitdir / common.read_text().strip()).resolve().parent
    return repo.parent / "shared" / "data"
