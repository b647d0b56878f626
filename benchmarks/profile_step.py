"""Where one training step's time goes: a torch.profiler trace of the training loop's steps.

    python -m benchmarks.profile_step --scene DIR [--backend ngp] [--preset fast] \
        [--warmup 200] [--steps 50] [--device cuda] [--variant NAME[=JSON]] [--threads N] \
        [--stacks] [--trace] [--out OUT]

The trainer runs with one hook (`ProfileSteps`): `--warmup` steps first (kernel compilation,
occupancy-grid warm-up, the allocator's pools), then `--steps` steps timed plainly and
`--steps` more under the profiler. Reported per step:
- wall: the trainer's step clock, synchronised with the device (as benchmarks.error_vs_time);
- host stages: inclusive CPU time of the named ranges the trainer and the ngp field open
  (grid_update, sample_rays, render > march / field / composite, loss, backward, optimizer);
- device (CUDA only): kernel time by kind — every kernel's name sorted into the op that
  launched it (Warp kernels by their Python names, cuBLAS GEMMs as "mlp", the fused Adam as
  "optimizer", the remaining PyTorch element-wise and reduction kernels as "torch other"),
  and the device's busy share of the wall time (kernel time / wall; low means the step waits on
  the host: launches, Python, a sync); every "torch other" kernel by name with its launches
  per step (`other_kernels`: what no kind claims is where a fusion is still to be had); the
  device's idle gaps between kernels and the host events running as each began, innermost
  and as a path outer to inner (`device_gaps`: what the GPU waits on; with `--stacks` the
  path holds the Python line of this repository too);
- synchronisations over 32 more steps: the implicit host-device ones (torch's sync debug
  mode, CUDA only) and the explicit ones by caller (`benchmarks.explicit_syncs`);
- CPU only: the ops with the most self CPU time (Warp kernels appear as their autograd
  functions, e.g. _HashGridEncodeBackward).
`--variant` trains one of benchmarks.cpu_preset's variants instead of the preset's defaults
(e.g. `before`: the GPU sizes and dense Adam, ngp on a CPU before issue #18); given several
times, each variant is profiled in turn (its run in OUT/NAME) and the report puts them side by
side first (one lease's call profiles a plain and a refined step, say).

Outputs in OUT: profile_step.json and profile_step.md (the table for benchmarks/RESULTS.md);
with several variants the JSON's "variants" holds one result each. `--trace`: the profiled
steps' events as a Chrome trace too (the run folder's trace.json.gz, chrome://tracing or
Perfetto), for what the tables cannot name; keep --steps small, a trace is ~1 MB a step.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import torch

from benchmarks.cli import add_run_arguments, benchmark_main
from benchmarks.cpu_preset import build, parse_variant
from benchmarks.curve import load_scene_dir, make_config
from benchmarks.device_gaps import device_gaps
from benchmarks.explicit_syncs import ExplicitSyncs
from benchmarks.session import session_info, write_report
from fastenerf.backends import BACKEND_NAMES
from fastenerf.errors import InputError
from fastenerf.hooks import Hook, trained_slots_now
from fastenerf.progress import progress_bar
from fastenerf.run import resolve_device

STAGES = (
    "grid_update",
    "sample_rays",
    "render",
    "march",
    "field",
    "composite",
    "loss",
    "backward",
    "optimizer",
)
# Kernel name -> kind, first match wins. Warp names a kernel after its Python function.
KERNEL_KINDS = (
    # the march's own helpers: the per-ray cap, the fixed buffers' slices and padding, the
    # single pass's copy out of its scratch (before the thirty-fourth session: "torch other")
    ("march", r"march|ray_aabb|cap_segments|reserve_slices|pad_tail|place_rows"),
    ("compaction", r"_compact|_visibility|prune"),
    ("ray points", r"_points_(forward|backward)"),
    # hashgrid.py builds its kernels in `_kernels()`: Warp names them _kernels__locals__NAME
    # (hashgrid_runs.py: run_backward__locals__backward_table_runs)
    ("hash grid", r"hash|grid_index|_kernels__locals__(forward|backward)|backward_table"),
    ("spherical harmonics", r"(^|_)sh_|spherical"),
    ("composite", r"composite|distortion"),
    ("occupancy grid", r"occup|lookup|bitfield|mark_unseen|grid_update|_cells"),
    ("event targets", r"window|event|bayer"),
    ("mlp", r"gemm|cutlass|xmma|nvjet|cublas|sm\d+_"),
    ("optimizer", r"adam|multi_tensor|foreach"),
)


# "torch other" kernels the Markdown lists (the JSON has them all).
OTHER_ROWS = 20

# Steps watched with torch's sync debug mode after the profile (it warns at every host sync).
SYNC_CHECK_STEPS = 32


def kernel_kind(name: str) -> str:
    """The op a CUDA kernel belongs to (see KERNEL_KINDS), else "torch other"."""
    low = name.lower()
    for kind, pattern in KERNEL_KINDS:
        if re.search(pattern, low):
            return kind
    return "torch other"


# A profiler range named Class.method#Class.method (Optimizer.step#Adam.step). A bare "#" is
# not enough: PyTorch's element-wise kernels carry "{lambda()#1}" in their template names, and
# dropping those left the bf16 activations out of every GPU profile before the thirty-eighth
# session (benchmarks/RESULTS.md).
_RANGE_NAME = re.compile(r"[\w.]+#[\w.]+")


def _is_annotation(ev) -> bool:
    """A range's own row on the device timeline (record_function, Optimizer.step#...): its span,
    not a kernel; counting it would count its kernels twice."""
    name = ev.name
    return (
        bool(getattr(ev, "is_user_annotation", False))
        or name in STAGES
        or _RANGE_NAME.fullmatch(name) is not None
    )


def _device_time_us(ev) -> float:
    for attr in ("self_device_time_total", "self_cuda_time_total"):
        v = getattr(ev, attr, None)
        if v is not None:
            return float(v)
    return 0.0


class ProfileSteps(Hook):
    """After `warmup` steps, times `steps` steps plainly, then `steps` more under
    torch.profiler, then stops the run; `result` holds the per-step breakdown."""

    def __init__(
        self,
        warmup: int,
        steps: int,
        progress: bool = True,
        stacks: bool = False,
        trace: Path | None = None,
    ):
        self.warmup, self.steps, self.stacks, self.trace = warmup, steps, stacks, trace
        self.phase = "warmup"
        self.count = 0
        self.wall: list[float] = []
        self.prof = None
        self.result: dict[str, Any] | None = None
        self.bar = progress_bar(
            total=warmup + 2 * steps + SYNC_CHECK_STEPS, desc="profile", enabled=progress
        )

    def on_start(self, trainer) -> None:
        # step times are the device's (the clock of error_vs_time): a device-paced step is
        # timed over a phase, settled at its ends, not synchronised one by one
        trainer.sync_clock = trainer.step_mode == "plain"
        if self.warmup == 0:
            self._next(trainer)

    def after_step(self, trainer, stats: dict[str, Any]) -> None:
        self.bar.update(1)
        self.count += 1
        limit = self.warmup if self.phase == "warmup" else self.steps
        if self.phase == "syncs":
            limit = SYNC_CHECK_STEPS
        if self.count >= limit:
            self._next(trainer)

    def _clock(self, trainer) -> float:
        trainer.settle_clock()
        return trainer.train_seconds

    @staticmethod
    def _captures(trainer) -> int | None:
        """CUDA graphs the run captured so far (None: no graphed step)."""
        return getattr(getattr(trainer, "graph", None), "captures", None)

    def _next(self, trainer) -> None:
        self.count = 0
        if self.phase == "warmup":
            # the same steps without the profiler first: its per-op bookkeeping slows the host
            self.phase, self.t_plain = "plain", self._clock(trainer)
            self.captures = [self._captures(trainer)]
        elif self.phase == "plain":
            from torch.profiler import ProfilerActivity, profile

            self.plain_ms = 1e3 * (self._clock(trainer) - self.t_plain) / self.steps
            self.captures.append(self._captures(trainer))
            dev = trainer.device
            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
            # with_stack: Python calls become host events, so a device gap's path (`device_gaps`)
            # names the line of this repository that made it
            self.prof = profile(activities=acts, with_stack=self.stacks)
            self.prof.__enter__()
            self.phase, self._last = "profiled", self._clock(trainer)
        elif self.phase == "profiled":
            self.wall = [(self._clock(trainer) - self._last) / self.steps] * self.steps
            self.prof.__exit__(None, None, None)
            if self.trace is not None:
                write_trace(self.prof, self.trace)
            self.result = breakdown(self.prof, trainer.device, self.wall, self.plain_ms)
            self.captures.append(self._captures(trainer))
            c = self.captures
            # a capture runs the step's Python once more and its eager warm-up steps: a
            # window with one shows their host time in the stages below, a replay none
            self.result["captures"] = (
                None if None in c else {"unprofiled": c[1] - c[0], "profiled": c[2] - c[1]}
            )
            self.phase = "syncs"
            self._watch_syncs(trainer, True)
        else:
            self._watch_syncs(trainer, False)
            self.phase = "done"
            trainer.request_stop()

    def _watch_syncs(self, trainer, on: bool) -> None:
        """Count the synchronisations of SYNC_CHECK_STEPS steps: the explicit ones (any
        device) and the implicit host-device ones (torch's sync debug mode, CUDA only)."""
        import warnings

        cuda = trainer.device.type == "cuda"
        if on:
            self._explicit = ExplicitSyncs().__enter__()
            if cuda:
                self._catch = warnings.catch_warnings(record=True)
                self._seen = self._catch.__enter__()
                warnings.simplefilter("always")
                torch.cuda.set_sync_debug_mode("warn")
            return
        self._explicit.__exit__(None, None, None)
        self.result["explicit_syncs_per_step"] = self._explicit.per_step(SYNC_CHECK_STEPS)
        self.result["explicit_sync_examples"] = self._explicit.examples()
        if not cuda:
            return
        torch.cuda.set_sync_debug_mode("default")
        self._catch.__exit__(None, None, None)
        syncs = [  # where each one was called from (the debug mode's own notice left out)
            f"{w.filename}:{w.lineno}"
            for w in self._seen
            if "called a synchronizing" in str(w.message)
        ]
        self.result["host_syncs_per_step"] = len(syncs) / SYNC_CHECK_STEPS
        self.result["host_sync_examples"] = sorted(set(syncs))[:10]

    def on_end(self, trainer, summary: dict[str, Any]) -> None:
        self.bar.close()
        if self.phase == "profiled":
            self.prof.__exit__(None, None, None)
        elif self.phase == "syncs":  # stopped early: the wrapped entry points restored
            self._watch_syncs(trainer, False)


def write_trace(prof, path: Path) -> None:
    """The profile's events as a gzipped Chrome trace at `path`, written atomically."""
    import gzip
    import os
    import shutil
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        raw = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(raw))
        packed = Path(tmp) / path.name
        with raw.open("rb") as src, gzip.open(packed, "wb", compresslevel=6) as dst:
            shutil.copyfileobj(src, dst)
        os.replace(packed, path)


def breakdown(prof, dev: torch.device, wall: list[float], plain_ms: float) -> dict[str, Any]:
    """Per-step host stages, device kernel time by kind and the device's busy share."""
    steps = len(wall)
    host = dict.fromkeys(STAGES, 0.0)
    for ev in prof.key_averages():
        if ev.key in host:
            host[ev.key] += ev.cpu_time_total / 1e3  # inclusive, ms over all steps
    kernels, spans, host_events = split_events(prof.events() if dev.type == "cuda" else [])
    tally = tally_kernels(kernels, steps)
    wall_ms = 1e3 * sum(wall) / steps
    device_ms = sum(tally["device_ms"].values())
    return {
        "steps": steps,
        "wall_ms_unprofiled": plain_ms,
        "wall_ms": wall_ms,
        "host_ms": {k: v / steps for k, v in host.items()},
        **tally,
        "device_busy_ms": device_ms if dev.type == "cuda" else None,
        "device_busy_share": device_ms / wall_ms if dev.type == "cuda" else None,
        "top_cpu_ops_ms": {} if dev.type == "cuda" else _top_cpu_ops(prof, steps),
        "device_gaps": device_gaps(spans, host_events, steps) if spans else None,
    }


def split_events(events) -> tuple[list, list, list]:
    """A profile's events split: the device kernels' (name, ms) and (start_us, end_us, name),
    and the host events' (start_us, end_us, name, thread) (ranges' own device rows left out)."""
    kernels, spans, host = [], [], []
    for ev in events:
        tr = getattr(ev, "time_range", None)
        if getattr(ev, "device_type", None) != torch.autograd.DeviceType.CUDA:
            if tr is not None:
                host.append((tr.start, tr.end, ev.name, getattr(ev, "thread", None)))
            continue
        if not _is_annotation(ev) and (us := _device_time_us(ev)):
            kernels.append((ev.name, us / 1e3))
            if tr is not None:
                spans.append((tr.start, tr.end, ev.name))
    return kernels, spans, host


def tally_kernels(kernels: list[tuple[str, float]], steps: int, top: int = 15) -> dict[str, dict]:
    """Per-step device time of profiled kernel launches `kernels` ((name, ms) each) over
    `steps` steps: `device_ms` by kind (KERNEL_KINDS), `top_kernels_ms` (the `top` largest
    by name) and `other_kernels` (every "torch other" kernel: ms and launches per step, the
    ones no kind claims, where the next fusion is found)."""
    kinds: dict[str, float] = {}
    by_name: dict[str, float] = {}
    other: dict[str, list[float]] = {}
    for name, ms in kernels:
        kind = kernel_kind(name)
        kinds[kind] = kinds.get(kind, 0.0) + ms
        by_name[name] = by_name.get(name, 0.0) + ms
        if kind == "torch other":
            row = other.setdefault(name[:120], [0.0, 0.0])
            row[0] += ms
            row[1] += 1
    largest = sorted(by_name.items(), key=lambda kv: -kv[1])
    return {
        "device_ms": {k: v / steps for k, v in sorted(kinds.items(), key=lambda kv: -kv[1])},
        "top_kernels_ms": {k[:120]: v / steps for k, v in largest[:top]},
        "other_kernels": {
            k: {"ms": ms / steps, "launches": n / steps}
            for k, (ms, n) in sorted(other.items(), key=lambda kv: -kv[1][0])
        },
    }


def _top_cpu_ops(prof, steps: int, n: int = 12) -> dict[str, float]:
    """The `n` ops with the most self CPU time, ms per step (named ranges left out)."""
    ops = [
        ev
        for ev in prof.key_averages()
        if ev.key not in STAGES and not _RANGE_NAME.fullmatch(ev.key)
    ]
    ops.sort(key=lambda ev: -ev.self_cpu_time_total)
    return {ev.key[:80]: ev.self_cpu_time_total / 1e3 / steps for ev in ops[:n]}


def _code_cell(name: str) -> str:
    """A kernel's or host event's name as a Markdown table cell (its pipes escaped)."""
    return "`" + name.replace("|", "\\|") + "`"


def markdown(res: dict) -> str:
    m = res["session"]["machine"]["name"]
    cpu = res["session"]["machine"]["cpu_numbers"]
    lines = [
        f"### Training step profile — {res['scene']}, {res['backend']} ({res['preset']}), {m}",
        "",
    ]
    if cpu:
        lines += ["**CPU numbers**: not comparable with GPU step times.", ""]
    samples = res.get("samples_per_step")
    lines += [
        f"{res['steps']} steps after {res['warmup']} warm-up steps; "
        f"{res['rays_per_step']} rays/step"
        + (f", {samples:,.0f} samples/step" if samples else "")
        + (
            f" ({res['samples_per_ray']:.1f} per ray kept of {res['marched_per_ray']:.1f} marched)"
            if res.get("marched_per_ray")
            else ""
        )
        + (f", {res['trained_slots']:,} slots" if res.get("trained_slots") else "")
        + f"; **{res['wall_ms_unprofiled']:.2f} ms/step** wall without the profiler, "
        f"{res['wall_ms']:.2f} ms under it"
        + (
            f"; device kernels {res['device_busy_ms']:.2f} ms/step "
            f"({100 * res['device_busy_ms'] / res['wall_ms_unprofiled']:.0f} % of the "
            "unprofiled step: the rest of the step the GPU waits on the host)"
            if res["device_busy_ms"] is not None
            else ""
        )
        + ".",
        "",
        "| host stage (inclusive CPU time) | ms/step |",
        "|---|---:|",
    ]
    for k, v in res["host_ms"].items():
        indent = "  ↳ " if k in ("march", "field", "composite") else ""
        lines.append(f"| {indent}{k} | {v:.2f} |")
    if res.get("top_cpu_ops_ms"):
        lines += ["", "| op (self CPU time) | ms/step |", "|---|---:|"]
        lines += [f"| {k} | {v:.2f} |" for k, v in res["top_cpu_ops_ms"].items()]
    if res["device_ms"]:
        lines += ["", "| device kernels by op | ms/step | share |", "|---|---:|---:|"]
        tot = sum(res["device_ms"].values()) or 1.0
        for k, v in res["device_ms"].items():
            lines.append(f"| {k} | {v:.3f} | {100 * v / tot:.0f} % |")
    if res.get("other_kernels"):
        lines += ["", '| "torch other" kernel | ms/step | launches/step |', "|---|---:|---:|"]
        for k, v in list(res["other_kernels"].items())[:OTHER_ROWS]:
            lines.append(f"| {_code_cell(k)} | {v['ms']:.3f} | {v['launches']:.1f} |")
    lines += _waits_lines(res)
    lines.append("")
    return "\n".join(lines)


def _idle_table(head: str, rows: dict[str, float]) -> list[str]:
    """A two-column Markdown table of idle ms/step by host event (path, kernel), after a
    blank."""
    out = ["", f"| {head} | idle ms/step |", "|---|---:|"]
    return out + [f"| {_code_cell(k)} | {v:.3f} |" for k, v in rows.items()]


def _waits_lines(res: dict) -> list[str]:
    """The Markdown of what the step waits on: the device's idle gaps, graph captures, host
    and explicit synchronisations."""
    lines: list[str] = []
    if res.get("device_gaps"):
        g = res["device_gaps"]
        lines += [
            "",
            f"Device idle between kernels (profiled steps): {g['idle_ms']:.3f} ms/step in "
            f"{g['gaps']:.1f} gaps (largest {g['largest_gap_ms']:.3f} ms); the host event "
            "running as each gap began (the training thread's):",
        ]
        lines += _idle_table("host event at the gap", g["idle_by_host_ms"])
        tables = [
            ("idle_by_path_ms", "host events at the gap, outer › inner"),
            ("idle_other_threads_ms", "another thread's host event at the gap (not the step's)"),
            ("idle_by_next_kernel_ms", "kernel that ended the gap"),
            ("idle_by_sync_lead_in_ms", "sync call at the gap, after the host events before it"),
        ]
        for key, head in tables:
            if g.get(key):
                lines += _idle_table(head, g[key])
    if res.get("captures"):
        c = res["captures"]
        lines += [
            "",
            f"CUDA graphs captured: {c['unprofiled']} in the unprofiled steps, "
            f"{c['profiled']} in the profiled ones (each with its eager warm-up steps; the "
            "host stages are those steps' and the captures' Python, a replay runs none).",
        ]
    if res.get("host_syncs_per_step") is not None:
        where = ", ".join(res.get("host_sync_examples") or []) or "none"
        lines += ["", f"Host syncs per step: {res['host_syncs_per_step']:.2f} (at {where})."]
    if res.get("explicit_syncs_per_step") is not None:
        where = ", ".join(res.get("explicit_sync_examples") or []) or "none"
        lines += [
            "",
            f"Explicit synchronisations per step: {res['explicit_syncs_per_step']:.2f} "
            f"(at {where}).",
        ]
    return lines


def profile_one(scene, args: argparse.Namespace, device, run_dir: Path, variant) -> dict:
    """One trainer profiled (`ProfileSteps`) in `run_dir`: the preset's, or `variant`'s
    (NAME, spec) from benchmarks.cpu_preset; the result dict `markdown` takes."""
    from fastenerf.train import Trainer

    backend = args.backend
    if variant:
        name, spec = variant
        trainer = build(scene, run_dir.name, spec, 300.0, run_dir.parent, str(device))
        backend = f"{spec.get('backend', 'ngp')}, variant {name}"
    else:
        cfg = make_config(args.backend, args.preset, 300.0, str(device))
        trainer = Trainer(scene, cfg, run_dir)
    trace = run_dir / "trace.json.gz" if args.trace else None
    hook = ProfileSteps(
        args.warmup, args.steps, progress=not args.quiet, stacks=args.stacks, trace=trace
    )
    trainer.run(hooks=[hook])
    if hook.result is None:
        raise InputError(f"the run ended after {trainer.step_count} steps, before the profile")
    res = hook.result
    hist = trainer.history[-args.steps :]
    spr = [h["samples_per_ray"] for h in hist if "samples_per_ray" in h]
    mpr = [h["marched_per_ray"] for h in hist if "marched_per_ray" in h]  # compaction on
    n_rays = trainer.cfg.rays_per_step
    res.update(
        scene=Path(args.scene).resolve().name,
        backend=backend,
        preset=args.preset,
        warmup=args.warmup,
        rays_per_step=n_rays,
        samples_per_ray=(sum(spr) / len(spr)) if spr else None,
        samples_per_step=(2 * n_rays * sum(spr) / len(spr)) if spr else None,
        marched_per_ray=(sum(mpr) / len(mpr)) if mpr else None,
        trained_slots=trained_slots_now(trainer),
        session=session_info(device, args.commit),
    )
    return res


def parse_variants(texts: list[str] | None) -> list[tuple[str, dict]]:
    """--variant NAME[=JSON] ... -> [(name, spec)], every name once (each is a run folder)."""
    variants = [parse_variant(t) for t in texts or []]
    names = [n for n, _ in variants]
    for n in names:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", n) or n in (".", ".."):
            raise InputError(f"--variant {n!r}: a name is letters, digits, '_', '-' and '.'")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"--variant {dup[0]}: given twice (each variant needs its own name)")
    return variants


def run(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.warmup < 0:
        raise InputError("--steps must be >= 1 and --warmup >= 0")
    variants = parse_variants(args.variant)
    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    scene = load_scene_dir(args.scene)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if len(variants) <= 1:
        res = profile_one(scene, args, device, out / "run", variants[0] if variants else None)
        write_report(out, "profile_step", res, markdown(res))
        return 0
    # several: one after another in this process, each in its own run folder, side by side
    rows = [profile_one(scene, args, device, out / name, (name, spec)) for name, spec in variants]
    res = {"variants": rows, "session": rows[0]["session"]}
    md = side_by_side(rows) + "\n" + "\n".join(markdown(r) for r in rows)
    write_report(out, "profile_step", res, md)
    return 0


def side_by_side(rows: list[dict]) -> str:
    """One line per profiled variant: the step, the device's share, samples, captures."""
    lines = [
        f"### Training step profiles side by side — {rows[0]['scene']}, "
        f"{rows[0]['session']['machine']['name']} (one process, one after another)",
        "",
        "| variant | ms/step | device ms | busy | samples/step | slots | captures |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        dev = r["device_busy_ms"]
        c = r.get("captures")
        lines.append(
            f"| {r['backend'].rpartition('variant ')[2]} | {r['wall_ms_unprofiled']:.2f} | "
            + (f"{dev:.2f} | {100 * dev / r['wall_ms_unprofiled']:.0f} % | " if dev else "— | — | ")
            + (f"{r['samples_per_step']:,.0f} | " if r.get("samples_per_step") else "— | ")
            + (f"{r['trained_slots']:,} | " if r.get("trained_slots") else "— | ")
            + (f"{c['unprofiled']} + {c['profiled']} |" if c else "— |")
        )
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene folder")
    p.add_argument("--backend", default="ngp", choices=list(BACKEND_NAMES))
    p.add_argument("--preset", default="fast")
    p.add_argument("--warmup", type=int, default=200, help="steps before the profile")
    p.add_argument("--steps", type=int, default=50, help="profiled steps")
    add_run_arguments(p, "runs/bench/profile_step")
    p.add_argument(
        "--variant",
        action="append",
        metavar="NAME[=JSON]",
        help="a benchmarks.cpu_preset variant (built-in name or NAME=JSON) instead of --preset; "
        "repeat it to profile several one after another, side by side (OUT/NAME each)",
    )
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument(
        "--stacks",
        action="store_true",
        help="record Python calls in the profile, so each device gap's path names the line "
        "of this repository it began in (slows the profiled host much more: for where, not "
        "how much)",
    )
    p.add_argument(
        "--trace",
        action="store_true",
        help="also write the profiled steps as a Chrome trace (RUN/trace.json.gz; ~1 MB a step)",
    )


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("profile_step", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
