"""Data-parallel training of one field: N ranks, each its own rays, one set of weights.

    torchrun --standalone --nproc-per-node 4 -m fastenerf.cli train SCENE --out RUN --data-parallel

Every rank builds the same Trainer; `make_data_parallel` then makes the ranks replicas:

- rank 0's state (weights, optimiser moments, step, clocks, RNGs) is broadcast to the others,
  so they start from one set of weights even when resuming;
- each rank > 0 re-seeds its ray sampler from (seed, rank, step): the ranks draw different
  rays, and the step's batch is their union, `rays_per_step` x N pixels;
- before every optimiser step, the gradients are averaged over the ranks (an all-reduce: the
  parameters of over `BUCKET_NUMEL` elements, ngp's hash table, in place, the rest flattened
  into one buffer). The event loss is a mean over the batch's pixels, so the average of the
  ranks' gradients is the gradient of the union batch's loss: N ranks take the step one
  process would take on the union batch. Every rank's Adam then applies the same update.
  The self-calibration's gradients (pose corrections, thresholds) are averaged with them, and
  the pose rows any rank's batch saw (`PoseCalibration.seen`: the rows the lazy row Adam
  steps and refine_decay shrinks) become their union: every rank steps them alike, so the
  corrections, their moments and their gate statistics stay one set, as one process would
  learn on the union batch.
  The global torch RNG stays the same on every rank (the occupancy-grid refresh of ngp draws
  from it, and must pick the same cells everywhere); the render's sample jitter, drawn from
  it too, is then the same numbers for different rays, which is no bias.

No `DistributedDataParallel`: the field's render is custom (Warp kernels, packed samples), and
a hook on the optimiser (`register_step_pre_hook`) sees every gradient once, after the whole
backward. A step whose loss is not finite on some rank skips backward and the optimiser step
there; that rank joins the step's all-reduce from the sync hook instead, and all ranks then
skip the update (as one process would on a union batch with a non-finite loss).

`DataParallelSync`, the last hook of every rank, keeps the loop in lockstep: after each step
the ranks agree on the training clock (the slowest rank's, so a time budget ends every rank
at the same step) and on stopping (Ctrl-C, SIGTERM from torchrun, a failure, a deadline on any
rank stops all after the same step). Rank 0 alone writes the run folder (its checkpoints hold
rank 0's sampler state); the others train in a scratch folder removed at the end. A resumed
data-parallel run continues rank 0's ray stream exactly; the other ranks' streams are new
(statistically the same, not bit-identical).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.distributed as dist

from . import train_state
from .distributed import World, current_world, destroy, init
from .hooks import DivergenceGuard, Hook, StopOnSignal, default_hooks
from .io import write_json

if TYPE_CHECKING:
    from .config import TrainConfig
    from .data.formats.native import Scene
    from .train import Trainer

# Parameters with at least this many elements are all-reduced in place, alone; smaller ones
# are copied into one flat buffer so that an MLP's dozen tensors cost one collective.
BUCKET_NUMEL = 1 << 20
RECORD = "data_parallel.json"
# torchrun's agent forwards a Ctrl-C to its workers, which also got it from the terminal: a
# second signal this soon after the first is the same Ctrl-C, not a request to abort.
REPEAT_S = 2.0


class GradientAverager:
    """Averages the gradients of `params` over the ranks: `reduce()`, run by a pre-hook of
    `optimizer` (when given) before each of its steps; `catch_up()` is the all-reduce of a
    rank that skipped its step (see the module docstring).

    params: the parameters, in the same order on every rank; device: where the flat buffer
    lives (the parameters' device; NCCL needs CUDA tensors); pose_cal: the run's
    `PoseCalibration` or None, whose `seen` rows become their union over the ranks in the
    same all-reduce.
    """

    def __init__(
        self,
        params: list[torch.nn.Parameter],
        world: World,
        device: torch.device,
        optimizer: torch.optim.Optimizer | None = None,
        pose_cal=None,
    ):
        self.params, self.world, self.device = list(params), world, device
        self.pose_cal = pose_cal
        self.big = [p for p in self.params if p.numel() >= BUCKET_NUMEL]
        self.small = [p for p in self.params if p.numel() < BUCKET_NUMEL]
        self.reduced = False  # this step's all-reduce is done
        self.finite_here = True  # this rank's loss was finite at the last reduce
        self.skipped = False  # some rank's loss was not finite: nobody updated
        self.handle = None
        if optimizer is not None:
            self.handle = optimizer.register_step_pre_hook(self._before_step)

    def _before_step(self, optimizer, args, kwargs) -> None:
        self.reduce(finite=True)

    def catch_up(self) -> None:
        """After a step: the all-reduce this rank missed (it skipped its update)."""
        if not self.reduced:
            self.reduce(finite=False)
        self.reduced = False

    def reduce(self, finite: bool = True) -> None:
        """Sum the gradients (zeros where a rank has none) and the count of ranks whose loss was
        finite; average, or drop every gradient (the optimiser then skips) if one was not."""
        n = self.world.size
        for p in self.params:
            if p.grad is None or not finite:
                p.grad = torch.zeros_like(p)
        flag = torch.full((1,), float(finite), device=self.device)
        seen = None if self.pose_cal is None else self.pose_cal.seen
        seen_part = [] if seen is None else [seen.reshape(-1).float()]
        flat = torch.cat([*(p.grad.reshape(-1).float() for p in self.small), *seen_part, flag])
        dist.all_reduce(flat)
        for p in self.big:
            dist.all_reduce(p.grad)
        self.reduced, self.finite_here = True, finite
        self.skipped = int(round(float(flat[-1]))) < n
        if self.skipped:
            for p in self.params:
                p.grad = None
            if seen is not None:  # nor does refine_decay shrink a row (the ranks stay alike)
                self.pose_cal.seen = torch.zeros_like(seen)
            return
        if seen is not None:  # a row any rank saw: every rank's row Adam steps it alike
            k = seen.numel()
            self.pose_cal.seen = (flat[-1 - k : -1] > 0).view_as(seen)
        flat.div_(n)
        offset = 0
        for p in self.small:
            k = p.numel()
            p.grad.copy_(flat[offset : offset + k].view_as(p))
            offset += k
        for p in self.big:
            p.grad.div_(n)

    def remove(self) -> None:
        if self.handle is not None:
            self.handle.remove()


def rank_sampler_seed(seed: int, rank: int, step: int) -> tuple[dict, int]:
    """(numpy bit-generator state, torch seed) of rank `rank`'s sampler from step `step`."""
    ss = np.random.SeedSequence([int(seed), int(rank), int(step)])
    np_state = np.random.default_rng(ss).bit_generator.state
    torch_seed = int(ss.spawn(1)[0].generate_state(1, np.uint64)[0] >> np.uint64(1))
    return np_state, torch_seed


def reseed_sampler(trainer: Trainer, rank: int) -> None:
    """Give rank `rank`'s sampler its own stream (rank 0 keeps the trainer's own)."""
    if rank == 0:
        return
    np_state, torch_seed = rank_sampler_seed(trainer.cfg.seed, rank, trainer.step_count)
    gen = torch.Generator(device=trainer.sampler.device).manual_seed(torch_seed)
    trainer.sampler.load_state_dict(
        {
            "windows": {"rng": np_state, "lengths": trainer.windows.lengths},
            "gen": gen.get_state(),
            "position": 0,
        }
    )


def broadcast_state(trainer: Trainer, world: World) -> None:
    """Rank 0's trainer state (weights, optimiser, step, clocks, RNGs) into every rank's."""
    obj = [train_state.cpu_copy(train_state.trainer_state(trainer)) if world.is_main else None]
    device = trainer.device if trainer.device.type == "cuda" else None
    dist.broadcast_object_list(obj, src=0, device=device)
    if not world.is_main:
        train_state.restore(trainer, obj[0])


def make_data_parallel(trainer: Trainer, world: World | None = None) -> DataParallelSync:
    """Make `trainer` this rank's replica of one data-parallel run (the group must be up).

    Broadcasts rank 0's state, re-seeds this rank's sampler, averages gradients (the field's
    and the self-calibration's) before each optimiser step. Returns the sync hook, which must
    be the LAST hook of `trainer.run`.
    """
    world = world or current_world()
    if not dist.is_initialized():
        raise RuntimeError("make_data_parallel needs a process group (distributed.init)")
    broadcast_state(trainer, world)
    reseed_sampler(trainer, world.rank)
    params = [p for g in trainer.optimizer.param_groups for p in g["params"]]
    pose_cal = None
    if trainer.selfcal is not None:  # poses and thresholds: their own optimisers step after
        ids = {id(p) for p in params}
        params += [p for p in trainer.selfcal.parameters() if id(p) not in ids]
        pose_cal = trainer.selfcal.pose_cal
    averager = GradientAverager(params, world, trainer.device, trainer.optimizer, pose_cal)
    return DataParallelSync(averager, world)


class DataParallelSync(Hook):
    """The last hook on every rank: the skipped all-reduce, then one agreement per step on the
    clock (max), stopping (any) and failure (any). Ctrl-C / SIGTERM set a flag here (the
    trainer stops at the next agreement); a repeat after `REPEAT_S` aborts (KeyboardInterrupt).
    on_end removes the gradient hook and, with `cleanup`, the scratch folder and the group."""

    def __init__(self, averager: GradientAverager, world: World):
        self.averager, self.world = averager, world
        self.signalled: float | None = None
        self.old: dict[int, Any] = {}
        self.scratch: Path | None = None
        self.leave_group = False

    def on_start(self, trainer: Trainer) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def handler(signum, frame):
            now = time.monotonic()
            if self.signalled is not None and now - self.signalled > REPEAT_S:
                raise KeyboardInterrupt
            self.signalled = self.signalled or now

        for sig in (signal.SIGINT, signal.SIGTERM):
            self.old[sig] = signal.signal(sig, handler)

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        self.averager.catch_up()
        if self.averager.skipped and self.averager.finite_here:
            trainer.skipped_steps += 1  # another rank's loss was not finite (it counts its own)
        stop = trainer.stopped or self.signalled is not None
        v = torch.tensor(
            [trainer.train_seconds, float(stop), float(trainer.failure is not None)],
            dtype=torch.float64,
            device=trainer.device,
        )
        dist.all_reduce(v, op=dist.ReduceOp.MAX)
        trainer.train_seconds = float(v[0])
        if v[2] > 0 and trainer.failure is None:
            trainer.fail("another data-parallel rank failed (see its output); training stopped")
        elif v[1] > 0:
            trainer.request_stop()

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        for sig, old in self.old.items():
            signal.signal(sig, old)
        self.old.clear()
        self.averager.remove()
        if self.scratch is not None:
            shutil.rmtree(self.scratch, ignore_errors=True)
        if self.leave_group:
            destroy()


def rank_hooks(trainer: Trainer, sync: DataParallelSync, progress: bool) -> list[Hook]:
    """Rank 0: `fastenerf train`'s hooks (its Ctrl-C handling replaced by the sync's); other
    ranks: the divergence guard. The sync last on every rank."""
    if sync.world.is_main:
        hooks = [h for h in default_hooks(trainer, progress) if not isinstance(h, StopOnSignal)]
    else:
        hooks = [DivergenceGuard()]
    return [*hooks, sync]


def record_world(trainer: Trainer, world: World, backend: str) -> None:
    """RUN/data_parallel.json: the world of each (re)start, with the step it started at."""
    path = Path(trainer.out_dir) / RECORD
    try:
        starts = list(json.loads(path.read_text())["starts"])
    except (OSError, ValueError, KeyError, TypeError):
        starts = []
    starts.append(
        {
            "step": trainer.step_count,
            "world_size": world.size,
            "backend": backend,
            "rays_per_step_per_rank": trainer.cfg.rays_per_step,
            "rays_per_step_total": trainer.cfg.rays_per_step * world.size,
        }
    )
    write_json(path, {"starts": starts})


def data_parallel_trainer(
    scene: Scene, cfg: TrainConfig, out_dir: str | Path, resume: bool, progress: bool = True
) -> tuple[Trainer, list[Hook]]:
    """`fastenerf train --data-parallel`: join torchrun's group and build this rank's replica.

    Rank 0 trains into `out_dir` (resuming it if asked); the others into a scratch folder, and
    their standard output goes to /dev/null (one rank prints). The device is cuda:LOCAL_RANK
    when CUDA is there and `cfg.device` names no other. Returns (trainer, hooks for its run);
    the run's end leaves the group.
    """
    from .errors import InputError
    from .run import CHECKPOINT
    from .train import Trainer

    if cfg.refine_restart:  # a new field mid-run would leave the ranks' gradient hooks behind
        raise InputError("refine_restart: one GPU only (not with --data-parallel)")
    if not resume and (Path(out_dir) / CHECKPOINT).exists():  # every rank refuses, not only 0
        raise InputError(
            f"{out_dir}: already holds a training run; pass --resume to "
            "continue it or choose another --out"
        )
    world = init()
    backend = dist.get_backend() if dist.is_initialized() else "none"
    if cfg.device in (None, "auto", "cuda"):
        cfg.device = str(world.device)
    scratch = None
    if not world.is_main:
        scratch = Path(tempfile.mkdtemp(prefix=f"fastenerf-rank{world.rank}-"))
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the life of the process
    try:
        trainer = Trainer(scene, cfg, scratch or out_dir, resume=resume and world.is_main)
        if not dist.is_initialized():
            print("--data-parallel outside torchrun (one rank): training as usual")
            return trainer, default_hooks(trainer, progress)
        # the ranks agree on skipping a step through the all-reduce, on the host
        trainer.set_step_mode("plain")
        sync = make_data_parallel(trainer, world)
    except BaseException:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
        destroy()
        raise
    sync.scratch, sync.leave_group = scratch, True
    if world.is_main:
        record_world(trainer, world, backend)
        print(
            f"data-parallel over {world.size} ranks ({backend}): "
            f"{cfg.rays_per_step * world.size} pixels per step in all"
        )
    return trainer, rank_hooks(trainer, sync, progress)
