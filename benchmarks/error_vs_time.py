"""Error against training time: ngp and vanilla trained side by side on the same machine.

    python -m benchmarks.error_vs_time --scenes DIR [DIR ...] --backends ngp vanilla \
        [--budget-s ngp=300 vanilla=480] [--preset fast] [--out OUT] [--device cuda] \
        [--eval-views 10] [--eval-scale 1.0] [--resume] [--max-wall-s 540]

Protocol (DESIGN §8):
- Each (scene, backend) trains with the `Trainer`, one `step()` at a time. The training clock
  reads `time.perf_counter()` after `torch.cuda.synchronize()`, around the steps only: set-up,
  evaluation and checkpoint writes are outside it (evaluation time is reported per point).
  The learning-rate schedule spans the backend's budget (`TrainConfig.minutes`).
- Before a run's clock starts, a throwaway copy of it takes `--warmup-steps` steps and one
  evaluation, so one-time costs (Warp kernel compilation, CUDA context, cuBLAS handles) are not
  charged to whichever backend happens to run first.
- At a schedule of training times (`--schedule`: "dense" 1, 1.5, 2, 3, 4, 5, 6, 8, 10, ... s
  for ngp, whose early points decide the time-to-PSNR ratio; "coarse" 1, 2, 4, 8, 15, 30, ...
  s for vanilla, whose evaluations cost seconds each; the budget always last), the field is
  evaluated as `fastenerf eval` does: `render_image` at `--eval-scale`,
  colour correction fitted over all evaluated views together, PSNR from the pooled MSE, SSIM.
  The views are every k-th test view (k = ceil(V / --eval-views)), the same for every backend
  and point. A point is taken at the first step whose clock passes a scheduled time, so its
  `train_s` is the true training time (a little past the schedule).
- A call can stop before the budgets are spent (`--max-wall-s`, SIGTERM, Ctrl-C): it writes a
  checkpoint and the outputs so far; `--resume` continues every run from its checkpoint, its
  training clock and curve carrying on.

Outputs in OUT: error_vs_time.json (every point, with machine, versions and git commit),
error_vs_time.png (PSNR and SSIM against training seconds), error_vs_time.md (the table for
benchmarks/RESULTS.md), and runs/<scene>-<backend>/ (the Trainer's run folder + curve.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.cli import benchmark_main
from fastenerf.errors import InputError
from fastenerf.io import atomic_path, write_json

REPO_ROOT = Path(__file__).resolve().parents[1]
# Nice geometric training times (s); the budget is always the last point. "dense" has ~6 points
# per decade so that a time to reach a PSNR is bracketed within a factor 1.5 (the ratio target
# is 50x: a factor-2 ladder could not tell 32x from 60x).
SCHEDULES = {
    "coarse": (1, 2, 4, 8, 15, 30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 14400),
    "dense": (
        1,
        1.5,
        2,
        3,
        4,
        5,
        6,
        8,
        10,
        12,
        15,
        20,
        25,
        30,
        40,
        50,
        60,
        90,
        120,
        180,
        240,
        300,
        450,
        600,
        900,
        1200,
        1800,
        3600,
        7200,
        14400,
    ),
}
SCHEDULE_S = SCHEDULES["coarse"]
DEFAULT_SCHEDULES = {"ngp": "dense", "vanilla": "coarse"}
DEFAULT_BUDGETS = {"ngp": 300.0, "vanilla": 480.0}
TARGET_SPEEDUP = 50.0
TARGET_GAP_DB = 0.5


# -- what, where, with what ----------------------------------------------------------------------


def schedule(budget_s: float, first_s: float = 1.0, ladder: str = "coarse") -> list[float]:
    """Training times (s) at which to evaluate: the nice geometric `ladder` (SCHEDULES) from
    `first_s` up to the budget, plus the budget itself; a budget below `first_s` gives
    [budget_s]."""
    if ladder not in SCHEDULES:
        raise InputError(f"--schedule: {ladder!r} is not one of {sorted(SCHEDULES)}")
    steps = SCHEDULES[ladder]
    times = [float(t) for t in steps if first_s <= t < budget_s]
    if first_s < steps[0]:  # sub-second starts (tiny CPU budgets): halve down from 1 s
        t = steps[0] / 2.0
        while t >= first_s:
            times.insert(0, t)
            t /= 2.0
        times = [x for x in times if x < budget_s]
    return sorted(set(times)) + [float(budget_s)]


def git_commit(root: str | Path = REPO_ROOT) -> str:
    """`git rev-parse HEAD` of the checkout (+ "-dirty" with uncommitted changes), or "unknown"."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}-dirty" if dirty else (head or "unknown")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine_info(device: torch.device) -> dict[str, Any]:
    """The machine a number was measured on: GPU name, or CPU model and core count."""
    info: dict[str, Any] = {
        "device": str(device),
        "host_cpu": cpu_model(),
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
    }
    if device.type == "cuda":
        info["name"] = torch.cuda.get_device_name(device)
        info["cpu_numbers"] = False
    else:
        info["name"] = (
            f"CPU: {info['host_cpu']} ({info['cpu_cores']} cores, "
            f"{info['torch_threads']} torch threads)"
        )
        info["cpu_numbers"] = True
    return info


def versions() -> dict[str, str]:
    try:
        import warp

        warp_version = warp.__version__
    except ImportError:
        warp_version = "not installed"
    from fastenerf import __version__

    return {
        "torch": torch.__version__,
        "warp": warp_version,
        "python": platform.python_version(),
        "fastenerf": __version__,
    }


def session_info(device: torch.device, commit: str | None = None) -> dict[str, Any]:
    """One benchmark call: machine, versions, commit, start time (UTC)."""
    return {
        "machine": machine_info(device),
        "versions": versions(),
        "git_commit": commit or git_commit(),
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def sync(device: torch.device) -> None:
    """Wait for queued GPU work (Warp launches on the same device included) before a clock read."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# -- evaluation exactly as `fastenerf eval` -------------------------------------------------------


@dataclasses.dataclass
class EvalSet:
    """Fixed test views of one scene: views (V,) indices into the scene's test views, their
    camera-to-worlds c2w (V, 4, 4), intrinsics at the evaluation scale, ground truth gt
    (V, H, W, 3) float32 display space, and the scene's near plane and background."""

    views: np.ndarray
    c2w: np.ndarray
    intrinsics: Any
    gt: np.ndarray
    near: float
    background: list[float] | None
    n_test: int
    scale: float


def make_eval_set(scene, n_views: int = 10, scale: float = 1.0) -> EvalSet:
    """Every k-th test view, k = ceil(V / n_views), at `scale` of the sensor resolution."""
    from fastenerf.data.rig import Intrinsics
    from fastenerf.evaluate import load_gt
    from fastenerf.train import scene_background

    sc = scene.config
    if scene.test_c2w is None or not scene.test_rgb_paths:
        raise InputError(
            f"{scene.root}: no ground-truth test views (test/poses.npz, test/rgb): "
            "cannot benchmark error against time"
        )
    n = len(scene.test_c2w)
    k = max(1, math.ceil(n / max(1, n_views)))
    views = np.arange(0, n, k)
    intr = Intrinsics.from_config(sc.intrinsics, sc.width, sc.height)
    if scale != 1.0:
        intr = intr.scaled(scale)
    gt = load_gt(scene, views, (intr.height, intr.width))
    return EvalSet(
        views, np.asarray(scene.test_c2w)[views], intr, gt, sc.near, scene_background(sc), n, scale
    )


def evaluate_field(field, ev: EvalSet, chunk: int = 16384) -> dict[str, float]:
    """Colour-corrected PSNR (pooled MSE) and mean SSIM of `field` on `ev`, as `fastenerf eval`
    computes them (no autocast, colours clamped to [0, 1] before the correction)."""
    from fastenerf.evaluate import color_correct, psnr, ssim
    from fastenerf.render import render_image

    pred = np.stack(
        [
            render_image(
                field, c2w, ev.intrinsics, near=ev.near, background=ev.background, chunk=chunk
            )["rgb"]
            .clamp(0, 1)
            .cpu()
            .numpy()
            for c2w in ev.c2w
        ]
    )
    corrected = color_correct(pred, ev.gt)
    return {
        "psnr": psnr(corrected, ev.gt),
        "ssim": ssim(corrected, ev.gt),
        "psnr_uncorrected": psnr(pred, ev.gt),
    }


# -- one timed run --------------------------------------------------------------------------------


class StopFlag:
    """Set by SIGTERM / the first Ctrl-C: the current step finishes, then the run checkpoints."""

    def __init__(self) -> None:
        self.set = False
        self._old: dict[int, Any] = {}

    def install(self) -> StopFlag:
        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                self._old[sig] = signal.signal(sig, self._handler)
            except ValueError:  # not the main thread
                pass
        return self

    def _handler(self, signum, frame) -> None:
        if self.set and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.set = True

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()


def read_curve(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def warm_up(scene, cfg, ev: EvalSet, steps: int, parent: Path) -> float:
    """Run `steps` steps and one evaluation on a throwaway trainer; returns the seconds taken."""
    from fastenerf.train import Trainer

    if steps <= 0:
        return 0.0
    t = time.perf_counter()
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".warmup-", dir=parent))
    try:
        tr = Trainer(scene, cfg, tmp)
        for _ in range(steps):
            tr.step()
        evaluate_field(
            tr.field, dataclasses.replace(ev, c2w=ev.c2w[:1], gt=ev.gt[:1]), tr.cfg.chunk
        )
        sync(tr.device)
        del tr
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return time.perf_counter() - t


def train_curve(
    scene,
    cfg,
    run_dir: str | Path,
    ev: EvalSet,
    times: list[float],
    *,
    label: dict[str, Any],
    session: dict[str, Any],
    resume: bool = False,
    deadline: float | None = None,
    stop: StopFlag | None = None,
    warmup_steps: int = 1,
    checkpoint_every_s: float = 60.0,
    progress: bool = True,
) -> dict[str, Any]:
    """Train `cfg` on `scene` in `run_dir`, evaluating on `ev` when the training clock passes
    each of `times` (s); returns the curve (also written to run_dir/curve.json).

    label: fields copied into the curve and every point (e.g. scene, backend); session: from
    `session_info`; resume: continue from run_dir's checkpoint and curve (a run without a
    checkpoint starts afresh); deadline: `time.perf_counter()` value after which the run
    checkpoints and returns unfinished; stop: a StopFlag checked after every step.
    Each point: train_s, step, psnr, ssim, psnr_uncorrected, eval_s, loss (mean over the steps
    since the previous point), samples_per_step, step_ms (mean), session (index into sessions).
    """
    from tqdm import tqdm

    from fastenerf.train import CHECKPOINT, Trainer

    run_dir = Path(run_dir)
    curve_path = run_dir / "curve.json"
    has_ckpt = (run_dir / CHECKPOINT).is_file()
    if has_ckpt and not resume:
        raise InputError(
            f"{run_dir}: already holds a benchmark run; pass --resume to continue "
            "it or choose another --out"
        )
    budget = float(times[-1])
    curve = (read_curve(curve_path) if has_ckpt else None) or {}
    curve.update(label)
    curve.update(
        budget_s=budget, schedule_s=list(times), eval_views=ev.views.tolist(), eval_scale=ev.scale
    )
    curve.setdefault("points", [])
    curve.setdefault("sessions", [])
    if has_ckpt and curve.get("train_s", 0.0) >= budget and curve.get("finished"):
        return curve  # nothing left to do for this budget
    if warmup_steps > 0 and not (stop and stop.set) and not _past(deadline):
        curve["last_warmup_s"] = warm_up(scene, cfg, ev, warmup_steps, run_dir.parent)
    trainer = Trainer(scene, cfg, run_dir, resume=has_ckpt)
    dev = trainer.device
    curve["train_config"] = trainer.cfg.to_dict()
    curve["session_started"] = len(curve["sessions"])
    curve["sessions"].append(session)
    sess = len(curve["sessions"]) - 1
    # Points logged after the checkpoint will be taken again (the curve is written first).
    curve["points"] = [p for p in curve["points"] if p["step"] <= trainer.step_count]
    train_s = trainer.train_seconds
    done_targets = {p.get("target_s") for p in curve["points"]}
    pending = [t for t in times if t > train_s and t not in done_targets]
    # each pixel is rendered at t0 and at t1; the pixels are split evenly over the windows
    w = trainer.cfg.windows_per_step
    rays = 2 * w * max(1, trainer.cfg.rays_per_step // w)
    acc = {"loss": 0.0, "n": 0, "samples": 0.0, "step_s": 0.0, "steps": 0}

    def save(finished: bool) -> None:
        curve.update(train_s=train_s, step=trainer.step_count, finished=finished)
        write_json(curve_path, jsonable(curve))  # curve first: see the resume rule above
        trainer.save_checkpoint(finished=finished)

    bar = tqdm(
        total=round(budget, 1),
        initial=round(min(train_s, budget), 1),
        unit="s",
        desc=f"{label.get('scene', '')} {trainer.cfg.backend}",
        disable=not progress,
        dynamic_ncols=True,
        leave=True,
        bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s {postfix}",
    )
    last_ckpt = time.perf_counter()
    try:
        sync(dev)
        while pending and not (stop and stop.set) and not _past(deadline):
            t0 = time.perf_counter()
            stats = trainer.step()
            sync(dev)
            dt = time.perf_counter() - t0
            train_s += dt
            trainer.train_seconds = train_s  # the synchronised clock goes into the checkpoint
            if math.isfinite(stats["loss"]):
                acc["loss"] += stats["loss"]
                acc["n"] += 1
            acc["samples"] += stats.get("samples_per_ray", float("nan")) * rays
            acc["step_s"] += dt
            acc["steps"] += 1
            if train_s >= pending[0]:
                target = pending.pop(0)
                while pending and train_s >= pending[0]:  # one long step passed several
                    target = pending.pop(0)
                te = time.perf_counter()
                metrics = evaluate_field(trainer.field, ev, trainer.cfg.chunk)
                sync(dev)
                eval_s = time.perf_counter() - te
                trainer.eval_seconds += eval_s
                curve["points"].append(
                    {
                        **label,
                        "target_s": target,
                        "train_s": train_s,
                        "step": trainer.step_count,
                        **metrics,
                        "eval_s": eval_s,
                        "loss": acc["loss"] / acc["n"] if acc["n"] else float("nan"),
                        "samples_per_step": acc["samples"] / max(acc["steps"], 1),
                        "step_ms": 1e3 * acc["step_s"] / max(acc["steps"], 1),
                        "session": sess,
                    }
                )
                acc = dict.fromkeys(acc, 0)
                bar.set_postfix_str(
                    f"psnr {metrics['psnr']:.2f} dB @ step {trainer.step_count}", refresh=False
                )
                save(finished=not pending)
                last_ckpt = time.perf_counter()
            elif time.perf_counter() - last_ckpt >= checkpoint_every_s:
                save(finished=False)
                last_ckpt = time.perf_counter()
            bar.n = round(min(train_s, budget), 1)
            bar.refresh()
        if pending:
            save(finished=False)
    finally:
        bar.close()
    curve["finished"] = not pending
    return curve


def _past(deadline: float | None) -> bool:
    return deadline is not None and time.perf_counter() >= deadline


def finite(x: Any) -> bool:
    """True for a finite number (None, NaN and inf are "no value")."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def jsonable(obj: Any) -> Any:
    """`obj` with non-finite floats as None, so the files are strict JSON."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    return obj


# -- summaries ------------------------------------------------------------------------------------


def best_point(points: list[dict]) -> dict | None:
    """The point of highest PSNR (the earliest of equals)."""
    ok = [p for p in points if finite(p["psnr"])]
    return max(ok, key=lambda p: (p["psnr"], -p["train_s"])) if ok else None


def time_to_reach(points: list[dict], psnr: float) -> dict[str, float | None] | None:
    """When a curve first reaches `psnr`: {"upper": train_s of the first point at or above it,
    "lower": train_s of the point before (0 if none), "interp": the crossing interpolated
    linearly in PSNR against log time between those two (None without a point before)}, or None
    if never reached."""
    pts = sorted((p for p in points if finite(p["psnr"])), key=lambda p: p["train_s"])
    for i, p in enumerate(pts):
        if p["psnr"] >= psnr:
            if i == 0:
                return {"upper": p["train_s"], "lower": 0.0, "interp": None}
            q = pts[i - 1]
            lo, hi = math.log(q["train_s"]), math.log(p["train_s"])
            # q is below psnr, p at or above: a proper crossing; a flat step gives hi
            f = (psnr - q["psnr"]) / (p["psnr"] - q["psnr"]) if p["psnr"] > q["psnr"] else 1.0
            return {
                "upper": p["train_s"],
                "lower": q["train_s"],
                "interp": math.exp(lo + f * (hi - lo)),
            }
    return None


def summarize_scene(runs: dict[str, dict]) -> dict[str, Any]:
    """The numbers of DESIGN §8 for one scene; runs: backend -> curve."""
    out: dict[str, Any] = {"backends": {}}
    for b, r in runs.items():
        pts = r["points"]
        best = best_point(pts)
        last = max(pts, key=lambda p: p["train_s"]) if pts else None
        out["backends"][b] = {
            "best_psnr": best and best["psnr"],
            "best_ssim": best and best["ssim"],
            "time_to_best_s": best and best["train_s"],
            "step_at_best": best and best["step"],
            "last_train_s": last and last["train_s"],
            "last_psnr": last and last["psnr"],
            "budget_s": r.get("budget_s"),
            "finished": bool(r.get("finished")),
            "n_points": len(pts),
        }
    ngp, van = runs.get("ngp"), runs.get("vanilla")
    if ngp and van and ngp["points"] and van["points"]:
        vb = best_point(van["points"])
        first = min(van["points"], key=lambda p: p["train_s"])
        # A vanilla run whose best is its first evaluation never learned within its budget:
        # that PSNR is what a near-empty field scores (high on a scene that is mostly known
        # background), and "time to reach it" measures nothing.
        learned = vb is not None and (len(van["points"]) == 1 or vb is not first)
        hit = time_to_reach(ngp["points"], vb["psnr"]) if learned else None
        t_v = vb and vb["train_s"]
        out["ngp_vs_vanilla"] = {
            "vanilla_learned": learned,
            "vanilla_best_psnr": vb and vb["psnr"],
            "vanilla_time_to_best_s": t_v,
            # the first ngp point at or above: an upper bound on the time, so `speedup` is a
            # lower bound; `speedup_interp` interpolates between the bracketing points
            "ngp_time_to_same_s": hit and hit["upper"],
            "ngp_time_to_same_lower_s": hit and hit["lower"],
            "ngp_time_to_same_interp_s": hit and hit["interp"],
            "speedup": (t_v / hit["upper"]) if hit else None,
            "speedup_upper": (t_v / hit["lower"]) if hit and hit["lower"] > 0 else None,
            "speedup_interp": (t_v / hit["interp"]) if hit and hit["interp"] else None,
            "reached": hit is not None,
        }
        if not learned:
            for k in ("speedup", "speedup_upper", "speedup_interp"):
                out["ngp_vs_vanilla"][k] = None
    if ngp and ngp["points"]:
        pts = sorted(ngp["points"], key=lambda p: p["train_s"])
        at60 = next((p for p in pts if p["train_s"] >= 60.0), None)
        last = pts[-1]
        if at60 is not None and at60 is not last and finite(at60["psnr"]) and finite(last["psnr"]):
            out["ngp_60s"] = {
                "psnr_at_60s": at60["psnr"],
                "train_s": at60["train_s"],
                "last_psnr": last["psnr"],
                "last_train_s": last["train_s"],
                "gap_db": last["psnr"] - at60["psnr"],
                "met": last["psnr"] - at60["psnr"] <= TARGET_GAP_DB,
            }
        else:
            out["ngp_60s"] = None
    return out


def _f(x, fmt: str = ".2f", none: str = "—") -> str:
    if not finite(x):
        return none
    return format(x, fmt)


def markdown(result: dict) -> str:
    """The Markdown table for benchmarks/RESULTS.md."""
    machines = result["machines"]
    cpu = result["cpu_numbers"]
    proto = result["protocol"]
    lines = [f"### Error against training time — {' / '.join(machines)}", ""]
    if cpu:
        lines += [
            f"**CPU numbers** (measured on {' / '.join(machines)}): reduced-size runs, "
            "not comparable with the GPU targets of DESIGN §8.",
            "",
        ]
    if len(machines) > 1:
        lines += [
            "**Warning:** the points were measured on more than one machine (resumed "
            "calls landed on different hardware); times are not comparable across them.",
            "",
        ]
    if not result["complete"]:
        lines += [
            "**Incomplete:** some runs have not spent their budget yet (continue with `--resume`).",
            "",
        ]
    lines += [
        f"Commit {', '.join(result['git_commits'])}; torch {', '.join(result['torch'])}, "
        f"warp {', '.join(result['warp'])}. Preset {proto['preset']}; budgets "
        + ", ".join(f"{b} {s:g} s" for b, s in proto["budgets_s"].items())
        + "; evaluation on every k-th test view ("
        + ", ".join(f"{s}: k = {k}" for s, k in proto["eval_every_k"].items())
        + f") at "
        f"{proto['eval_scale']:g}× resolution, colour-corrected over all evaluated views "
        "together, PSNR from the pooled MSE. Training time excludes evaluation, checkpoints "
        f"and a {proto['warmup_steps']}-step warm-up (kernel compilation). Times to a PSNR are "
        "those of the first evaluation point at or above it, so they are upper bounds and the "
        "speed-ups lower bounds (the point before is given after the dash; schedules: "
        + "; ".join(
            f"{b} {lad} " + ", ".join(f"{t:g}" for t in SCHEDULES[lad][:12]) + " … s"
            for b, lad in proto.get("schedules", {"all": "coarse"}).items()
        )
        + ").",
        "",
        "| scene | backend | best PSNR | SSIM there | train s to best | steps | last point s "
        "| PSNR there |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, s in result["summary"].items():
        for b, v in s["backends"].items():
            flag = "" if v["finished"] else " (unfinished)"
            lines.append(
                f"| {scene} | {b}{flag} | {_f(v['best_psnr'])} | "
                f"{_f(v['best_ssim'], '.3f')} | {_f(v['time_to_best_s'], '.1f')} | "
                f"{_f(v['step_at_best'], 'd')} | {_f(v['last_train_s'], '.1f')} | "
                f"{_f(v['last_psnr'])} |"
            )
    lines += [
        "",
        "| scene | vanilla best PSNR | vanilla s to best | ngp s to same PSNR (point before) "
        f"| speed-up (target ≥ {TARGET_SPEEDUP:g}×) | ngp PSNR at 60 s | ngp PSNR last "
        f"(s) | gap (target ≤ {TARGET_GAP_DB:g} dB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, s in result["summary"].items():
        c = s.get("ngp_vs_vanilla")
        g = s.get("ngp_60s")
        if c is None:
            cmp = "| — | — | — | — (needs both backends) "
        elif not c.get("vanilla_learned", True):
            cmp = (
                f"| {_f(c['vanilla_best_psnr'])} | {_f(c['vanilla_time_to_best_s'], '.1f')} "
                "| — | none: vanilla never rose above its first evaluation "
            )
        elif not c["reached"]:
            ngp_b = s["backends"]["ngp"]
            cmp = (
                f"| {_f(c['vanilla_best_psnr'])} | {_f(c['vanilla_time_to_best_s'], '.1f')} "
                f"| not reached in {_f(ngp_b['last_train_s'], '.0f')} s | not reached "
            )
        else:
            met = "met" if c["speedup"] >= TARGET_SPEEDUP else "not met"
            interp = (
                f"; {c['speedup_interp']:.0f}× interpolated" if finite(c["speedup_interp"]) else ""
            )
            cmp = (
                f"| {_f(c['vanilla_best_psnr'])} | {_f(c['vanilla_time_to_best_s'], '.1f')} "
                f"| {_f(c['ngp_time_to_same_s'], '.1f')} "
                f"({_f(c['ngp_time_to_same_lower_s'] or None, '.1f', 'first point')}) "
                f"| ≥ {c['speedup']:.1f}× ({met}{interp}) "
            )
        if g is None:
            gap = "| n/a (ngp budget ≤ 60 s or no ngp run) | — | — |"
        else:
            gap = (
                f"| {_f(g['psnr_at_60s'])} ({_f(g['train_s'], '.0f')} s) | "
                f"{_f(g['last_psnr'])} ({_f(g['last_train_s'], '.0f')}) | "
                f"{g['gap_db']:+.2f} dB ({'met' if g['met'] else 'not met'}) |"
            )
        lines.append(f"| {scene} " + cmp + gap)
    lines += [
        "",
        "The vanilla backend's best is its best within its budget, not its converged "
        "value (the reference trains for days); where that best is its first evaluation "
        "(an untrained field's score) there is no speed-up to report. ngp's last point stands "
        "in for its "
        "converged PSNR. Each run's learning rate decays over its own budget, so ngp's 60 s "
        "point of a longer run is taken mid-schedule (a run with `--budget-s ngp=60` measures "
        "a 60 s schedule).",
        "",
    ]
    return "\n".join(lines)


def collect(curves: list[dict], protocol: dict) -> dict:
    """The error_vs_time.json object from the run curves."""
    points, machines, commits, torch_v, warp_v = [], [], [], [], []
    for c in curves:
        for p in c["points"]:
            s = c["sessions"][p["session"]]
            points.append(
                {
                    **p,
                    "machine": s["machine"]["name"],
                    "device": s["machine"]["device"],
                    "torch": s["versions"]["torch"],
                    "warp": s["versions"]["warp"],
                    "git_commit": s["git_commit"],
                }
            )
        for s in c["sessions"]:
            for lst, v in (
                (machines, s["machine"]["name"]),
                (commits, s["git_commit"]),
                (torch_v, s["versions"]["torch"]),
                (warp_v, s["versions"]["warp"]),
            ):
                if v not in lst:
                    lst.append(v)
    by_scene: dict[str, dict[str, dict]] = {}
    for c in curves:
        by_scene.setdefault(c["scene"], {})[c["backend"]] = c
    cpu = any(s["machine"]["cpu_numbers"] for c in curves for s in c["sessions"])
    return {
        "benchmark": "error_vs_time",
        "cpu_numbers": cpu,
        "machines": machines,
        "git_commits": commits,
        "torch": torch_v,
        "warp": warp_v,
        "complete": all(c.get("finished") for c in curves),
        "protocol": protocol,
        "summary": {s: summarize_scene(r) for s, r in by_scene.items()},
        "runs": curves,
        "points": points,
    }


def write_outputs(result: dict, out: Path) -> dict[str, Path]:
    from benchmarks.plots import plot_error_vs_time

    paths = {
        "json": out / "error_vs_time.json",
        "png": out / "error_vs_time.png",
        "md": out / "error_vs_time.md",
    }
    write_json(paths["json"], jsonable(result))
    title = ("CPU numbers — " if result["cpu_numbers"] else "") + " / ".join(result["machines"])
    plot_error_vs_time(result["runs"], paths["png"], title)
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(markdown(result))
    return paths


# -- the command ----------------------------------------------------------------------------------


def parse_budgets(items: list[str], backends: list[str]) -> dict[str, float]:
    """["ngp=300", "vanilla=480"] or ["60"] (every backend) -> {backend: seconds}."""
    out = {b: DEFAULT_BUDGETS.get(b, 60.0) for b in backends}
    for item in items or []:
        key, _, val = item.rpartition("=")
        try:
            sec = float(val)
        except ValueError:
            raise InputError(f"--budget-s: {item!r} is not BACKEND=SECONDS or SECONDS") from None
        if not (sec > 0 and math.isfinite(sec)):
            raise InputError(f"--budget-s: {item!r}: seconds must be positive")
        if key and key not in backends:
            raise InputError(f"--budget-s: {key!r} is not one of the --backends {backends}")
        for b in [key] if key else backends:
            out[b] = sec
    return out


def parse_presets(items: list[str], backends: list[str]) -> dict[str, str]:
    """["fast"] or ["ngp=fast", "vanilla=eventnerf"] -> {backend: preset}."""
    out = dict.fromkeys(backends, "fast")
    for item in items or []:
        key, _, val = item.rpartition("=")
        if key and key not in backends:
            raise InputError(f"--preset: {key!r} is not one of the --backends {backends}")
        for b in [key] if key else backends:
            out[b] = val
    return out


def parse_schedules(items: list[str], backends: list[str]) -> dict[str, str]:
    """["dense"] or ["ngp=dense", "vanilla=coarse"] -> {backend: ladder name}."""
    out = {b: DEFAULT_SCHEDULES.get(b, "coarse") for b in backends}
    for item in items or []:
        key, _, val = item.rpartition("=")
        if key and key not in backends:
            raise InputError(f"--schedule: {key!r} is not one of the --backends {backends}")
        if val not in SCHEDULES:
            raise InputError(f"--schedule: {val!r} is not one of {sorted(SCHEDULES)}")
        for b in [key] if key else backends:
            out[b] = val
    return out


def parse_sets(items: list[str], backends: list[str]) -> dict[str, dict[str, dict]]:
    """--set [BACKEND:]KEY=JSON_VALUE -> {backend: {"train": {...}, "backend_options": {...}}}.

    KEY is a TrainConfig field, else a backend option (NGPOptions / VanillaField argument).
    """
    from fastenerf.config import TrainConfig

    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    out = {b: {"train": {}, "backend_options": {}} for b in backends}
    for item in items or []:
        lhs, eq, raw = item.partition("=")
        if not eq:
            raise InputError(f"--set: {item!r} is not [BACKEND:]KEY=VALUE")
        who, _, key = lhs.rpartition(":")
        if who and who not in backends:
            raise InputError(f"--set: {who!r} is not one of the --backends {backends}")
        try:
            val = json.loads(raw)
        except json.JSONDecodeError:
            val = raw  # a bare word: a string
        for b in [who] if who else backends:
            out[b]["train" if key in fields else "backend_options"][key] = val
    return out


def make_config(
    backend: str,
    preset: str,
    budget_s: float,
    device: str,
    train: dict | None = None,
    backend_options: dict | None = None,
):
    """The TrainConfig of one benchmark run: preset + overrides, lr schedule over the budget."""
    from fastenerf.config import train_preset

    train = dict(train or {})
    opts = {**train.pop("backend_options", {}), **(backend_options or {})}
    train.update(minutes=budget_s / 60.0, device=device, eval_every_s=0.0, checkpoint_every_s=0.0)
    cfg = train_preset(preset, backend, **train)
    cfg.backend_options = {**cfg.backend_options, **opts}  # keep the preset's budget-made choices
    return cfg


def load_scene_dir(path: str | Path):
    from fastenerf.data.formats import load_any
    from fastenerf.data.formats.native import Scene

    scene = load_any(path)
    if not isinstance(scene, Scene):
        raise InputError(f"{path}: not a scene folder")
    return scene


def scene_labels(dirs: list[str]) -> list[str]:
    """Folder names, made unique with -2, -3, ... (two folders may share a name)."""
    labels: list[str] = []
    for d in dirs:
        name = Path(d).resolve().name or "scene"
        label, i = name, 2
        while label in labels:
            label, i = f"{name}-{i}", i + 1
        labels.append(label)
    return labels


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scenes",
        nargs="+",
        required=True,
        metavar="DIR",
        help="scene folders with ground-truth test views",
    )
    p.add_argument("--backends", nargs="+", default=["ngp", "vanilla"], choices=["ngp", "vanilla"])
    p.add_argument(
        "--budget-s",
        nargs="+",
        default=[],
        metavar="[BACKEND=]S",
        help="training seconds per backend (default ngp=300 vanilla=480)",
    )
    p.add_argument(
        "--preset",
        nargs="+",
        default=["fast"],
        metavar="[BACKEND=]NAME",
        help="training preset, for all or per backend (default fast)",
    )
    p.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="[BACKEND:]KEY=VALUE",
        help="TrainConfig field or backend option (JSON value), e.g. "
        "rays_per_step=4096 ngp:log2_table_size=21",
    )
    p.add_argument("--out", default="runs/bench/error_vs_time", help="output folder")
    p.add_argument("--device", default="auto", help="cuda, cuda:N, cpu or auto")
    p.add_argument(
        "--eval-views",
        type=int,
        default=10,
        help="evaluate every k-th test view so that about this many are used",
    )
    p.add_argument(
        "--eval-scale",
        type=float,
        default=1.0,
        help="evaluation resolution as a fraction of the sensor's",
    )
    p.add_argument(
        "--schedule",
        nargs="+",
        default=[],
        metavar="[BACKEND=]LADDER",
        help="evaluation times: dense or coarse, for all or per backend "
        "(default ngp=dense vanilla=coarse)",
    )
    p.add_argument(
        "--first-s", type=float, default=1.0, help="first scheduled evaluation (s of training)"
    )
    p.add_argument(
        "--warmup-steps",
        type=int,
        default=2,
        help="steps of a throwaway run before the clock starts (0: none)",
    )
    p.add_argument(
        "--resume", action="store_true", help="continue the runs in --out from their checkpoints"
    )
    p.add_argument(
        "--max-wall-s",
        type=float,
        default=None,
        help="stop (checkpoint, write outputs) after this many wall seconds",
    )
    p.add_argument(
        "--commit", default=None, help="git commit to record (for copies of the tree without .git)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from fastenerf.train import resolve_device

    t_start = time.perf_counter()
    deadline = None if args.max_wall_s is None else t_start + args.max_wall_s
    if args.eval_views < 1 or args.eval_scale <= 0:
        raise InputError("--eval-views must be >= 1 and --eval-scale > 0")
    backends = list(dict.fromkeys(args.backends))
    budgets = parse_budgets(args.budget_s, backends)
    presets = parse_presets(args.preset, backends)
    sets = parse_sets(args.set, backends)
    ladders = parse_schedules(args.schedule, backends)
    device = resolve_device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    session = session_info(device, args.commit)
    scenes = [load_scene_dir(d) for d in args.scenes]
    labels = scene_labels(args.scenes)
    # Validate every configuration before the first minute of training is spent.
    cfgs = {b: make_config(b, presets[b], budgets[b], str(device), **sets[b]) for b in backends}
    if session["machine"]["cpu_numbers"]:
        print(f"CPU numbers: {session['machine']['name']}")
    stop = StopFlag().install()
    curves: list[dict] = []
    protocol: dict[str, Any] = {
        "preset": ", ".join(sorted(set(presets.values()))),
        "presets": presets,
        "budgets_s": budgets,
        "schedules": ladders,
        "overrides": sets,
        "eval_views": args.eval_views,
        "eval_scale": args.eval_scale,
        "eval_every_k": {},
        "warmup_steps": args.warmup_steps,
        "device": str(device),
        "clock": "perf_counter around Trainer.step() after torch.cuda.synchronize(); "
        "evaluation, checkpoints and set-up excluded",
        "color_correction": None,
    }
    from fastenerf.evaluate import COLOR_CORRECTION

    protocol["color_correction"] = COLOR_CORRECTION
    paths: dict[str, Path] = {}
    try:
        for scene, label, sdir in zip(scenes, labels, args.scenes, strict=True):
            ev = make_eval_set(scene, args.eval_views, args.eval_scale)
            protocol["eval_every_k"][label] = (
                int(ev.views[1] - ev.views[0]) if len(ev.views) > 1 else ev.n_test
            )
            for b in backends:
                run_dir = out / "runs" / f"{label}-{b}"
                curve = train_curve(
                    scene,
                    cfgs[b],
                    run_dir,
                    ev,
                    schedule(budgets[b], args.first_s, ladders[b]),
                    label={"scene": label, "backend": b, "scene_dir": str(Path(sdir).resolve())},
                    session=session,
                    resume=args.resume,
                    deadline=deadline,
                    stop=stop,
                    warmup_steps=args.warmup_steps,
                    progress=not args.quiet,
                )
                curves.append(curve)
                paths = write_outputs(collect(curves, protocol), out)
    finally:
        stop.restore()
    result = collect(curves, protocol)
    paths = write_outputs(result, out)
    for k in ("json", "png", "md"):
        print(f"wrote {paths[k]}")
    if not result["complete"]:
        print("incomplete: budgets not spent yet; run again with --resume to continue")
    else:
        print(markdown(result))
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("error_vs_time", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    sys.exit(main())
