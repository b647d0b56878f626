"""The motion prior's residual rotation error: the pose study's error, smoothed, per window.

    python -m benchmarks.prior_residual SCENE [SCENE ...] --levels 1 2 --windows 201 401 801
        [--order 1] [--json OUT.json]

For each scene and pose-error level, the training poses get the pose study's per-pose turn
(`perturb_training_data`, its seed), the motion prior (`smooth_poses`) is fitted with each
window, and the mean rotation error left against the exact poses is printed as a Markdown
table (degrees). No training: this is where pose refinement starts, and it is exact (the same
numbers on any machine). A window longer than the poses allow is reported as "—".
"""

from __future__ import annotations

import argparse
import math

from fastenerf.config import PerturbConfig
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.io import read_json_object, write_json
from fastenerf.outputs import OutputKind, claim_output
from fastenerf.perturb import perturb_training_data, pose_grid_times, rotation_angles_deg
from fastenerf.pose_smoothing import MIN_WINDOW, smoothed_rig

from .cli import benchmark_main


def _is_ours(p) -> bool:
    try:
        return "residual_deg" in read_json_object(p)
    except (InputError, OSError):
        return False


# --json: a file of this benchmark's (replaced), never any other JSON (a scene.json, a run's)
RESIDUAL_JSON = OutputKind("prior-residual JSON file", False, _is_ours)


def residuals(scene, level: float, windows: list[int], order: int) -> dict:
    """{"given": error before, window: error after (None where the window does not fit)}, mean
    rotation error in degrees over the training pose grid."""
    t = pose_grid_times(scene.config)
    rig, _, _ = perturb_training_data(scene, PerturbConfig(pose_error_deg=level))
    exact = scene.rig().pose(t)
    given = rotation_angles_deg(exact[:, :3, :3], rig.pose(t)[:, :3, :3]).mean()
    out: dict = {"given": float(given)}
    for w in windows:
        try:
            _, rep = smoothed_rig(rig, t, w, exact, order)
        except InputError:  # longer than the poses allow
            out[w] = None
            continue
        out[w] = rep["error_after_deg"]
    return out


def _fmt(v) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v:.4f}"


def _run(a: argparse.Namespace) -> int:
    bad = [w for w in a.windows if w < MIN_WINDOW or w % 2 == 0]
    if bad:
        raise InputError(f"--windows: each must be odd and >= {MIN_WINDOW}, got {bad[0]}")
    if not all(0 <= v <= 180 for v in a.levels):
        raise InputError(f"--levels: degrees in [0, 180], got {a.levels}")
    if a.json:
        claim_output(a.json, RESIDUAL_JSON, force=None, flag="--json")  # before any work
    rows, table = [], {}
    head = "| scene | level | given | " + " | ".join(f"window {w}" for w in a.windows) + " |"
    rows += [head, "|" + "---|" * (3 + len(a.windows))]
    for path in a.scenes:
        scene = load_scene_folder(path)
        for level in a.levels:
            r = residuals(scene, level, a.windows, a.order)
            table[f"{path} {level}"] = {str(k): v for k, v in r.items()}
            cells = [_fmt(r.get("given"))] + [_fmt(r[w]) for w in a.windows]
            rows.append(f"| {path} | {level:g}° | " + " | ".join(cells) + " |")
    print("\n".join(rows))
    if a.json:
        write_json(a.json, {"order": a.order, "residual_deg": table})
    return 0


def _args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenes", nargs="+", help="scene folders")
    p.add_argument("--levels", type=float, nargs="+", default=[1.0, 2.0], help="degrees")
    p.add_argument("--windows", type=int, nargs="+", default=[201, 401, 601, 801])
    p.add_argument("--order", type=int, default=1, choices=(1, 2))
    p.add_argument("--json", help="also write the table here")


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("prior_residual", __doc__, _args, _run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
