"""Evaluation against ground-truth views (DESIGN §9): colour correction, PSNR, SSIM, LPIPS.

Events only observe log-intensity *changes*, so the absolute exposure (and per-channel gain)
of the reconstruction is unobservable. As the reference does, before any metric the
prediction is mapped per channel by the affine least-squares fit gt ≈ A·pred + B in the
domain f(x) = log(x**2.2 + 0.1), over all test images of the scene together, then back with
f⁻¹(y) = (exp(y) − 0.1)**(1/2.2), clipped to [0, 1]. PSNR is from the MSE over all images
together; SSIM (scikit-image) and LPIPS (AlexNet) are averaged over views.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .data.formats.native import Scene
from .data.rig import Intrinsics
from .errors import InputError
from .io import write_image, write_json
from .progress import progress_bar
from .run import load_run, read_progress, scene_background

GAMMA = 2.2
LOG_EPS = 0.1
COLOR_CORRECTION = (
    "per-channel affine least-squares fit gt ≈ A·pred + B in log(x**2.2 + 0.1) "
    "over all test views together, mapped back with (exp(y) − 0.1)**(1/2.2), "
    "clipped to [0, 1] (as the EventNeRF reference)"
)


def to_log(x: np.ndarray) -> np.ndarray:
    return np.log(np.clip(x, 0.0, None) ** GAMMA + LOG_EPS)


def from_log(y: np.ndarray) -> np.ndarray:
    return np.clip(np.exp(y) - LOG_EPS, 0.0, None) ** (1.0 / GAMMA)


def fit_color_correction(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel (A (3,), B (3,)) of gt ≈ A·pred + B in the log domain; inputs (..., 3)."""
    p = to_log(np.asarray(pred, np.float64)).reshape(-1, 3)
    g = to_log(np.asarray(gt, np.float64)).reshape(-1, 3)
    a, b = np.ones(3), np.zeros(3)
    for k in range(3):
        design = np.stack([p[:, k], np.ones_like(p[:, k])], 1)
        (a[k], b[k]), *_ = np.linalg.lstsq(design, g[:, k], rcond=None)
    return a, b


def color_correct(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """pred (V, H, W, 3) corrected towards gt (V, H, W, 3) as the module docstring says.

    Returns float32 (V, H, W, 3) in [0, 1].
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise InputError(
            f"color_correct: pred {pred.shape} and gt {gt.shape} must both be (V, H, W, 3)"
        )
    a, b = fit_color_correction(pred, gt)
    return np.clip(from_log(a * to_log(pred) + b), 0.0, 1.0).astype(np.float32)


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR in dB (peak 1) from the MSE over all pixels of all images."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2))
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean SSIM over views (scikit-image, channel_axis=-1, data_range=1); (V, H, W, 3)."""
    from skimage.metrics import structural_similarity

    vals = []
    for p, g in zip(pred, gt, strict=True):
        win = min(7, *p.shape[:2])
        win -= 1 - win % 2  # odd window no larger than the image
        vals.append(structural_similarity(p, g, channel_axis=-1, data_range=1.0, win_size=win))
    return float(np.mean(vals))


def lpips_weights_path() -> Path:
    """Where torchvision keeps the AlexNet weights LPIPS needs."""
    import torch

    return Path(torch.hub.get_dir()) / "checkpoints" / "alexnet-owt-7be5be79.pth"


def lpips_score(pred: np.ndarray, gt: np.ndarray) -> tuple[float | None, str]:
    """Mean LPIPS (AlexNet) over views, or (None, why) when it cannot be computed offline.

    Never downloads: the `lpips` package and the AlexNet weights must already be on disk.
    """
    try:
        import lpips  # type: ignore[import-not-found]
    except ImportError:
        return None, "LPIPS: the 'lpips' package is not installed"
    weights = lpips_weights_path()
    lin = Path(lpips.__file__).parent / "weights" / "v0.1" / "alex.pth"
    for path in (weights, lin):
        if not path.is_file():
            return None, f"LPIPS: weights not found at {path}"
    import torch

    model = lpips.LPIPS(net="alex", verbose=False)
    p = torch.from_numpy(np.asarray(pred, np.float32)).permute(0, 3, 1, 2) * 2 - 1
    g = torch.from_numpy(np.asarray(gt, np.float32)).permute(0, 3, 1, 2) * 2 - 1
    with torch.no_grad():
        return float(model(p, g).mean()), "LPIPS: AlexNet"


def error_map(pred: np.ndarray, gt: np.ndarray, vmax: float = 0.25) -> np.ndarray:
    """|pred − gt| averaged over channels, as a colour image (H, W, 3) via matplotlib's magma."""
    from matplotlib import colormaps

    err = np.abs(pred - gt).mean(-1) / vmax
    return colormaps["magma"](np.clip(err, 0, 1))[..., :3].astype(np.float32)


def comparison_sheet(pred: np.ndarray, gt: np.ndarray, max_rows: int = 8) -> np.ndarray:
    """Rows of [pred | gt | error] for up to `max_rows` evenly chosen views, (H', W', 3)."""
    v = len(pred)
    rows = np.unique(np.linspace(0, v - 1, min(v, max_rows)).round().astype(int))
    gap = np.ones((pred.shape[1], 2, 3), np.float32)
    lines = [np.concatenate([pred[i], gap, gt[i], gap, error_map(pred[i], gt[i])], 1) for i in rows]
    hgap = np.ones((2, lines[0].shape[1], 3), np.float32)
    out = []
    for line in lines:
        out += [line, hgap]
    return np.concatenate(out[:-1], 0)


def quick_psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """Colour-corrected PSNR (the progress bar's number)."""
    return psnr(color_correct(pred, gt), gt)


# -- the one evaluation path: which views, at which scale, and how a field is scored ------------


def eval_view_indices(n_test: int, max_views: int | None = None) -> np.ndarray:
    """THE rule for which test views an evaluation uses: all of them, or `max_views` evenly
    spaced ones (linspace over [0, n_test − 1], first and last included, rounded, unique)."""
    if max_views is None or max_views >= n_test:
        return np.arange(n_test)
    return np.unique(np.linspace(0, n_test - 1, max(1, max_views)).round().astype(int))


@dataclass
class EvalSet:
    """Fixed test views of one scene, ready to score a field on.

    views: (V,) indices into the scene's test views; c2w: (V, 4, 4) float64 camera-to-world;
    intrinsics: `Intrinsics` at the evaluation scale; gt: (V, H, W, 3) float32 display space;
    near: world units; background: (3,) display-space colour or None; n_test: test views in
    the scene; scale: fraction of the sensor resolution.
    """

    views: np.ndarray
    c2w: np.ndarray
    intrinsics: Intrinsics
    gt: np.ndarray
    near: float
    background: list[float] | None
    n_test: int
    scale: float

    def subset(self, k: int) -> EvalSet:
        """The first `k` views (a warm-up render, say)."""
        return dataclasses.replace(self, views=self.views[:k], c2w=self.c2w[:k], gt=self.gt[:k])


def make_eval_set(scene: Scene, max_views: int | None = None, scale: float = 1.0) -> EvalSet:
    """The evaluation set of a loaded scene: views by `eval_view_indices`, at `scale`."""
    sc = scene.config
    if scene.test_c2w is None or not scene.test_rgb_paths:
        raise InputError(f"{scene.root}: no ground-truth test views (test/poses.npz, test/rgb)")
    if not (scale > 0 and math.isfinite(scale)):
        raise InputError(f"evaluation scale must be a positive number, got {scale}")
    n = len(scene.test_c2w)
    views = eval_view_indices(n, max_views)
    intr = Intrinsics.from_config(sc.intrinsics, sc.width, sc.height)
    if scale != 1.0:
        intr = intr.scaled(scale)
    gt = load_gt(scene, views, (intr.height, intr.width))
    c2w = np.asarray(scene.test_c2w)[views]
    return EvalSet(views, c2w, intr, gt, sc.near, scene_background(sc), n, scale)


def render_eval_set(field, ev: EvalSet, chunk: int = 16384, progress: bool = False) -> np.ndarray:
    """Render `field` from every view of `ev`: (V, H, W, 3) float32 in [0, 1] (clamped)."""
    from .render import render_image

    preds = []
    for c2w in progress_bar(ev.c2w, desc="eval", unit="view", enabled=progress):
        img = render_image(
            field, c2w, ev.intrinsics, near=ev.near, background=ev.background, chunk=chunk
        )
        preds.append(img["rgb"].clamp(0, 1).cpu().numpy())
    return np.stack(preds)


def score(pred: np.ndarray, gt: np.ndarray) -> tuple[dict[str, float], np.ndarray]:
    """Metrics of pred against gt (both (V, H, W, 3)) after the colour correction.

    Returns ({psnr, ssim, psnr_uncorrected}, corrected (V, H, W, 3) float32).
    """
    corrected = color_correct(pred, gt)
    metrics = {
        "psnr": psnr(corrected, gt),
        "ssim": ssim(corrected, gt),
        "psnr_uncorrected": psnr(pred, gt),
    }
    return metrics, corrected


def evaluate_field(
    field, ev: EvalSet, chunk: int = 16384, progress: bool = False
) -> tuple[dict[str, float], np.ndarray]:
    """Render and score `field` on `ev` (no autocast; colours clamped before the correction):
    what `fastenerf eval`, the trainer's periodic evaluation and every benchmark report.

    Returns (metrics with render_seconds_per_view, corrected predictions (V, H, W, 3)).
    """
    t = time.perf_counter()
    with torch.no_grad():
        pred = render_eval_set(field, ev, chunk, progress)
    render_s = time.perf_counter() - t
    metrics, corrected = score(pred, ev.gt)
    metrics["render_seconds_per_view"] = render_s / len(ev.views)
    return metrics, corrected


def evaluate_run(
    run_dir: str | Path,
    *,
    max_views: int | None = None,
    scale: float = 1.0,
    out_dir: str | Path | None = None,
    chunk: int | None = None,
    progress: bool = True,
) -> dict:
    """Render the scene's test views from a trained run, correct colours, score, save pictures.

    run_dir: a training run (RUN/config.json + RUN/checkpoint.pt); max_views: evenly chosen
    subset of the test views (None: all); scale: render (and compare) at this fraction of the
    sensor resolution (ground truth is resized with anti-aliasing). Writes metrics.json,
    corrected PNGs and a pred | gt | error sheet into out_dir (default RUN/eval/, and then
    RUN/metrics.json too); an `out_dir` elsewhere leaves the run folder untouched.
    """
    run_dir = Path(run_dir)
    field, scene, cfg = load_run(run_dir)
    if not isinstance(scene, Scene):
        raise InputError(f"{run_dir}: the run's scene folder is not available, cannot evaluate")
    ev = make_eval_set(scene, max_views, scale)
    metrics, corrected = evaluate_field(field, ev, chunk or cfg.chunk, progress)
    lp, lp_note = lpips_score(corrected, ev.gt)
    if lp is None:
        print(lp_note)
    info = read_progress(run_dir)
    metrics.update(
        lpips=lp,
        lpips_note=lp_note,
        n_views=len(ev.views),
        views=ev.views.tolist(),
        resolution=[ev.intrinsics.width, ev.intrinsics.height],
        train_seconds=info.get("train_seconds"),
        steps=info.get("step"),
        backend=cfg.backend,
        preset=cfg.preset,
        color_correction=COLOR_CORRECTION,
        scene=scene.config.name,
    )
    in_run = out_dir is None
    out_dir = run_dir / "eval" if in_run else Path(out_dir)
    for k, i in enumerate(ev.views):
        write_image(out_dir / f"{int(i):04d}.png", corrected[k])
    sheet = out_dir / "sheet.png"
    write_image(sheet, comparison_sheet(corrected, ev.gt))
    metrics["images"] = str(out_dir)
    metrics["sheet"] = str(sheet)
    write_json(out_dir / "metrics.json", metrics)
    if in_run:
        write_json(run_dir / "metrics.json", metrics)
    return metrics


def load_gt(scene, views: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Ground-truth test images `views` (V, H, W, 3) float32, resized to size (H, W) if needed."""
    import imageio.v3 as iio

    imgs = []
    for i in views:
        path = scene.test_rgb_paths[int(i)]
        try:
            img = iio.imread(path)[..., :3].astype(np.float32) / 255.0
        except Exception as e:  # noqa: BLE001 - any decoder error is a bad input file
            raise InputError(f"{path}: cannot read ground-truth image ({e})") from None
        if img.shape[:2] != tuple(size):
            from skimage.transform import resize

            img = resize(img, size, anti_aliasing=True).astype(np.float32)
        imgs.append(img)
    return np.stack(imgs)


def format_metrics(m: dict) -> str:
    lp = "n/a" if m.get("lpips") is None else f"{m['lpips']:.3f}"
    return (
        f"PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.3f}  LPIPS {lp}  "
        f"({m['n_views']} views, colour-corrected)"
    )


def load_metrics(run_dir: str | Path) -> dict:
    path = Path(run_dir) / "metrics.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: cannot read metrics ({e})") from None
