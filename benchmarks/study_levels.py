"""The robustness studies of the supplement (H, I, J) and one beside them: their levels, what
each level changes in the training configuration, and the supplement's own numbers to compare
with.

pose-error  every training pose's rotation turned by X° about its own random axis (test
            poses exact); levels in degrees
mount-error every training pose turned by X° about ONE random axis in the camera's own frame
            (a camera mis-mounted on its turntable; learnt back by refine_poses +
            refine_shared); levels in degrees; no supplement numbers
noise       uniformly random events added to the training stream, X % of the clean count;
            levels in percent
ablation    the method's choices switched off one at a time (training knobs): constant short
            window, constant long window, (almost) no negative sampling, no distortion loss

Windows are measured in views of the scene's pose grid (`SceneConfig.n_views` per loop). The
authors' synthetic ablations use constant windows of 10 and 50 poses of a 1000-pose loop (the
supplement's 10 ms / 100 ms are real data), so the short and long windows here are 1 % and 5 %
of the loop, whatever the scene's pose rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from fastenerf.config import PerturbConfig
from fastenerf.errors import InputError

SHORT_WINDOW_FRACTION = 0.01  # of the loop's views: the authors' 10 of 1000 poses
LONG_WINDOW_FRACTION = 0.05  # 50 of 1000
AUTHORS_NEG_RATIO = 0.001  # the authors' "no negative sampling" config (vs 0.1)
BREAK_DROP_DB = 3.0  # "the first level more than this below level 0's PSNR"


@dataclass(frozen=True)
class Study:
    """One study: its default levels, their unit, and the supplement's PSNR per level (dB,
    "Drums", EventNeRF's own training of ~5·10^5 steps)."""

    name: str
    levels: tuple
    numeric: bool
    unit: str  # "deg", "%" or "" (named variants)
    axis: str  # plot axis label
    supplement: dict = field(default_factory=dict)
    supplement_note: str = ""
    perturb: str = ""  # the PerturbConfig field a level sets ("" : training knobs)
    divisor: float = 1.0  # that field's value is level / divisor (percent -> fraction: 100)
    report: str = ""  # its key in RUN/config.json["perturbation"] (what the trainer measured)
    slug: str = ""  # the run folders' prefix: "pose" -> runs/pose-1deg


STUDIES: dict[str, Study] = {
    "pose-error": Study(
        "pose-error",
        (0.0, 0.01, 0.1, 0.3, 0.5, 1.0, 2.0),
        True,
        "deg",
        "pose error (degrees, every training pose)",
        {0.0: 27.43, 0.01: 27.26, 0.1: 26.18, 1.0: 18.11, 2.0: 17.49},
        "supplement I, Fig. 11: Drums, PSNR (dB)",
        "pose_error_deg",
        1.0,
        "pose",
        "pose",
    ),
    "mount-error": Study(
        "mount-error",
        (0.0, 0.5, 1.0, 2.0, 5.0),
        True,
        "deg",
        "mount error (degrees, one camera-frame turn shared by every training pose)",
        {},
        "none — the supplement has no mount-error study (ours, beside its pose study; "
        "docs/self-calibration.md)",
        "mount_error_deg",
        1.0,
        "mount",
        "mount",
    ),
    "noise": Study(
        "noise",
        (0.0, 1.0, 5.0, 15.0, 30.0),
        True,
        "%",
        "noise events (% of the clean event count)",
        {0.0: 27.43, 1.0: 27.35, 5.0: 27.36, 15.0: 27.31},
        "supplement J, Fig. 12: Drums, PSNR (dB)",
        "noise_fraction",
        100.0,
        "noise",
        "noise",
    ),
    "ablation": Study(
        "ablation",
        ("full", "short", "long", "no-negatives", "no-distortion-loss"),
        False,
        "",
        "variant",
        {},
        "supplement H, Fig. 10 (real 'Sewing'): qualitative only — full best; short window "
        "artefacts; long window blur; no negatives: artefacts around the object",
        slug="ablation",
    ),
}
# The studies whose levels turn the training poses (degrees): the same ranges, labels, pose
# stats (the error refinement leaves), table columns and plot units.
POSE_STUDIES = frozenset(name for name, spec in STUDIES.items() if spec.unit == "deg")

ABLATION_HELP = {
    "full": "the fast preset as it is (window U{1..5 % of the loop}, negatives, distortion loss)",
    "short": "constant short window: win_min = win_max = 1 % of the loop's views",
    "long": "constant long window: win_min = win_max = 5 % of the loop's views",
    "no-negatives": f"neg_ratio = {AUTHORS_NEG_RATIO:g} (the authors' config; the full: 0.1)",
    "no-distortion-loss": "distortion_weight = 0 (the full: 1e-4 on synthetic scenes)",
}


def window_views(fraction: float, n_views: int) -> int:
    """A window of `fraction` of the loop, in views (at least 1)."""
    return max(1, int(round(fraction * n_views)))


def level_overrides(study: str, level: Any, n_views: int, seed: int) -> dict[str, Any]:
    """TrainConfig overrides of one level: a PerturbConfig (pose, noise) or training knobs.

    level: degrees (pose-error, mount-error), percent (noise) or a variant name (ablation);
    n_views: views per loop of the scene; seed: the perturbation seed.
    """
    spec = STUDIES.get(study)
    if spec is None:
        raise InputError(f"unknown study {study!r} (choose from {sorted(STUDIES)})")
    if spec.perturb:
        value = float(level) / spec.divisor
        return {"perturb": PerturbConfig(**{spec.perturb: value}, seed=seed).validate()}
    if level == "full":
        return {}
    if level == "short":
        w = window_views(SHORT_WINDOW_FRACTION, n_views)
        return {"win_min": w, "win_max": w}
    if level == "long":
        w = window_views(LONG_WINDOW_FRACTION, n_views)
        return {"win_min": w, "win_max": w}
    if level == "no-negatives":
        return {"neg_ratio": AUTHORS_NEG_RATIO}
    if level == "no-distortion-loss":
        return {"distortion_weight": 0.0}
    raise InputError(f"ablation: unknown variant {level!r} (choose from {list(ABLATION_HELP)})")


def parse_levels(study: str, items: list[str] | None) -> list:
    """--levels for `study` (None: the defaults): numbers in ascending order for the pose
    studies (degrees, [0, 180)) and noise (percent, [0, 1000]); variant names for ablation."""
    spec = STUDIES[study]
    if not items:
        return list(spec.levels)
    if not spec.numeric:
        bad = [x for x in items if x not in ABLATION_HELP]
        if bad:
            raise InputError(f"--levels: unknown variant(s) {bad}; known: {list(ABLATION_HELP)}")
        if len(set(items)) != len(items):
            raise InputError("--levels: a variant is named twice")
        return list(items)
    poses = study in POSE_STUDIES
    hi, unit = (180.0, "degrees") if poses else (1000.0, "percent")
    out = []
    for x in items:
        try:
            v = float(x)
        except ValueError:
            raise InputError(f"--levels: {x!r} is not a number ({unit})") from None
        ok = math.isfinite(v) and 0.0 <= v and (v < hi if poses else v <= hi)
        if not ok:
            raise InputError(f"--levels: {x} is outside [0, {hi:g}{')' if hi == 180 else ']'}")
        out.append(v)
    if len(set(out)) != len(out):
        raise InputError("--levels: a level is given twice")
    return sorted(out)


def level_label(study: str, level: Any) -> str:
    """Short text of a level: "0.1°", "5 %", "short"."""
    if study in POSE_STUDIES:
        return f"{level:g}°"
    if study == "noise":
        return f"{level:g} %"
    return str(level)


def level_slug(study: str, level: Any) -> str:
    """The run folder's name of a level: "pose-0.1deg", "mount-2deg", "noise-5pct",
    "ablation-short"."""
    spec = STUDIES[study]
    if not spec.numeric:
        return f"{spec.slug}-{level}"
    return f"{spec.slug}-{level:g}{'deg' if study in POSE_STUDIES else 'pct'}"


def locate_break(levels: list[float], psnr: list[float | None]) -> dict[str, Any] | None:
    """Where a curve of PSNR against ascending numeric levels breaks.

    Returns {"largest_drop": {"from", "to", "drop_db"} — the adjacent pair (one level step)
    with the largest PSNR fall, "first_below": the first level whose PSNR is more than
    BREAK_DROP_DB under the first level's (None if none), "reference_db": that first
    level's PSNR}, or None without two finite points. Levels without a number are skipped.
    """
    pts = [(lv, p) for lv, p in zip(levels, psnr, strict=True) if _finite(p)]
    if len(pts) < 2:
        return None
    drops = [(a[1] - b[1], a[0], b[0]) for a, b in zip(pts, pts[1:], strict=False)]
    drop, lo, hi = max(drops, key=lambda d: d[0])
    ref_level, ref = pts[0]
    first = next((lv for lv, p in pts[1:] if p < ref - BREAK_DROP_DB), None)
    return {
        "largest_drop": {"from": lo, "to": hi, "drop_db": drop},
        "first_below": first,
        "threshold_db": BREAK_DROP_DB,
        "reference_level": ref_level,
        "reference_db": ref,
    }


def supplement_break(study: str) -> dict[str, Any] | None:
    """`locate_break` on the supplement's own numbers (None for the ablation)."""
    sup = STUDIES[study].supplement
    if not sup:
        return None
    levels = sorted(sup)
    return locate_break(levels, [sup[lv] for lv in levels])


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
