"""Timed camera poses on disk: an npz with t (M,) int64 µs and c2w (M, 4, 4) float64.

Below both the scene formats and the rig (each reads poses files), so neither imports the other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import read_npz, savez

__all__ = ["load_poses", "save_poses"]


def load_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(t (M,) int64 µs, c2w (M, 4, 4) float64) from a poses npz, validated."""
    path = Path(path)
    z = read_npz(path, ("t", "c2w"), what="poses file")
    t, c2w = z["t"], z["c2w"]
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
        raise InputError(f"{path}: 'c2w' must be (M, 4, 4), got {c2w.shape}")
    if t.shape != (len(c2w),):
        raise InputError(f"{path}: {len(c2w)} poses but 't' has shape {t.shape}")
    if t.dtype.kind not in "iuf" or (t.dtype.kind == "f" and not np.all(np.isfinite(t))):
        raise InputError(f"{path}: 't' must be finite numbers (µs), got dtype {t.dtype}")
    if not np.all(np.isfinite(c2w)):
        i = int(np.flatnonzero(~np.isfinite(c2w).reshape(len(c2w), -1).all(1))[0])
        raise InputError(f"{path}: pose {i} contains NaN or inf")
    return t.astype(np.int64), c2w.astype(np.float64)


def save_poses(path: str | Path, t: np.ndarray, c2w: np.ndarray) -> Path:
    return savez(path, t=np.asarray(t, np.int64), c2w=np.asarray(c2w, np.float64))
