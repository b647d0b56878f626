"""A training step replayed from a CUDA graph (issue #17): one launch for the whole step.

The device-paced step (`device_step`) no longer waits for the device, but its host still issues
every kernel of the step (~150 launches, each a few µs of Python and driver time), so a step
whose kernels are short is paced by the host. Here the render, the loss, the backward, the
finite-loss guard and the fused Adam update are captured once into a CUDA graph and replayed:

- **Static inputs.** The batch is copied into buffers the graph reads (`_Static`); the ray
  jitter is drawn into one too, outside the graph, from the same generator and in the same order
  as the device path draws it, so both paths take the same steps.
- **Learning rates** as device tensors the fused Adam and the pose rows' Adam read
  (`optim.lr_as_tensors`, `RowAdam.lr_as_tensors`), filled in place before each replay, as are
  pose refinement's coarse-to-fine level weights (`coarse_to_fine`).
- **What the graph bakes in** is the field's `graph_key()` (the fixed sample buffers'
  capacities, the march's cone, whether level weights apply), the self-calibration's (whether
  the poses step) and the batch shape; when it changes (the capacity follows the scene's
  carving), the step runs eagerly for `WARMUP` steps on a side stream and is captured again.
  With `keys` > 1 the graphs of that many keys are kept, each with the field's buffers it
  writes (`Field.graph_state`) and its gradients, so a capacity that returns to a recent size
  (it turns back and forth at a quantum's edge) replays its graph instead of capturing anew.
- **Stats** are one stacked vector the graph writes; each step's copy of it goes to the
  trainer's pending stats, so nothing reads the device per step.

Where nothing is captured (a CPU, `capture=False`) the same body runs eagerly on the same static
buffers: the path the tests compare with the plain step. A capture that fails falls back to that
eager path for the rest of the run, with one warning.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import torch

from .optim import lr_as_tensors
from .sampling import RayBatch

# Eager steps with an unchanged key before a capture (torch's rule: warm up on a side stream so
# lazily made state, e.g. the optimiser's moments and cuBLAS workspaces, exists before capture).
WARMUP = 2

# Kept graphs (`keys` > 1) hold their memory pools: a key is kept only while at least this
# share of the device's memory is free, else every kept graph is let go.
KEEP_FREE_SHARE = 0.25

# body(batch) -> (out, loss, parts): render, loss, backward and update of one batch; the loss
# and parts are 0-dim device tensors.
StepBody = Callable[[RayBatch], tuple[dict, torch.Tensor, dict]]


@dataclass
class _Static:
    """The batch fields a step reads, in buffers a graph can be replayed on."""

    rays_o: torch.Tensor  # (2B, 3) float32
    rays_d: torch.Tensor  # (2B, 3) float32
    target: torch.Tensor  # (B,) float32
    channel: torch.Tensor | None  # (B,) int64 or None (mono)
    jitter: torch.Tensor  # (2B,) float32 uniform [0, 1) march offsets
    # with thresholds applied in the step: (B, 2), (B,)
    parts: torch.Tensor | None = None
    pix: torch.Tensor | None = None
    # with pose refinement: (B, 3) camera-frame directions, (2B,) int64 grid rows
    dirs: torch.Tensor | None = None
    pose_idx: torch.Tensor | None = None

    @classmethod
    def like(cls, batch: RayBatch) -> _Static:
        def like(t):
            return None if t is None else torch.empty_like(t)

        with_parts = batch.parts is not None
        return cls(
            torch.empty_like(batch.rays_o),
            torch.empty_like(batch.rays_d),
            torch.empty_like(batch.target),
            like(batch.channel),
            torch.empty(len(batch.rays_o), device=batch.rays_o.device),
            like(batch.parts),
            like(batch.pix) if with_parts else None,
            like(batch.dirs) if batch.pose_idx is not None else None,
            like(batch.pose_idx),
        )

    def fill(self, batch: RayBatch) -> RayBatch:
        """Copy `batch` in; returns a RayBatch whose tensors are these buffers."""
        fields = dict(rays_o=self.rays_o, rays_d=self.rays_d, target=self.target)
        fields.update(channel=self.channel)
        if self.parts is not None:
            fields.update(parts=self.parts, pix=self.pix)
        if self.pose_idx is not None:
            fields.update(dirs=self.dirs, pose_idx=self.pose_idx)
        for k, buf in fields.items():
            if buf is not None:
                buf.copy_(getattr(batch, k))
        torch.rand(len(self.jitter), out=self.jitter)  # the device path's draw, same order
        return RayBatch(**{**batch.__dict__, **fields})


@dataclass
class _Kept:
    """A key's graphs put aside for a later return: with their outputs, the gradients they
    write (set back as the parameters' .grad) and the field's buffers they read and write."""

    graphs: list
    outs: list
    grads: list
    field_state: object


def release_generator(device: torch.device) -> None:
    """Unmark the device's default generator after a capture that failed at its end: torch ends
    a capture's mark on the generators it registered only when the capture succeeded, and every
    later draw from a marked one raises ("Offset increment outside graph capture"). Its state
    (seed, offset) moves to an unmarked state object; a generator that is not marked is left."""
    if device.type != "cuda":
        return
    index = device.index if device.index is not None else torch.cuda.current_device()
    gen = torch.cuda.default_generators[index]
    fresh = torch.Generator(device)
    fresh.set_state(gen.get_state())
    gen.graphsafe_set_state(fresh.graphsafe_get_state())


def batch_key(batch: RayBatch) -> tuple:
    """The shapes a graph of this batch bakes in."""
    ch = batch.channel
    shapes = (tuple(batch.rays_o.shape), tuple(batch.target.shape), batch.parts is not None)
    return (*shapes, batch.pose_idx is not None, None if ch is None else ch.dtype)


def graphed_step(
    body: StepBody,
    field,
    optimizer,
    calibration,
    device: torch.device,
    capture: bool | None,
    copies: int = 1,
    keys: int = 1,
) -> GraphedStep | None:
    """A `GraphedStep` of `body` where the step can be captured (the field has a `graph_key`,
    the self-calibration, if any, is `capturable`), with the field's and the calibration's
    learning rates made device tensors; None, every lr left as it was, where it cannot."""
    if field.graph_key() is None or not (calibration is None or calibration.capturable):
        return None
    lr_as_tensors(optimizer, device)
    if calibration is not None:
        calibration.lr_as_tensors(device)
    return GraphedStep(body, field, device, capture, calibration, copies, keys)


class GraphedStep:
    """Runs `body` on static copies of each batch, replayed from a CUDA graph where it can.

    body: see `StepBody`; field: the trained field (its `graph_key()` and `train_jitter`);
    capture: capture graphs (default: on CUDA); calibration: the run's `SelfCalibration` or
    None (its `graph_key()` joins the field's, its parameters' gradients are the graph's too);
    copies: graphs captured of each key, replayed in turn (`TrainConfig.graph_copies`);
    keys: the most keys whose graphs are kept, the current one included, the least recently
    used put down first (`TrainConfig.graph_keys`; 1: a new key drops the old graphs).
    Attributes: captures (graphs captured so far), failure (why capture was given up, or None),
    replays (steps replayed), returns (key changes that found their graphs kept).
    """

    def __init__(
        self,
        body: StepBody,
        field,
        device: torch.device,
        capture: bool | None = None,
        calibration=None,
        copies: int = 1,
        keys: int = 1,
    ):
        self.body, self.field, self.device = body, field, torch.device(device)
        self.calibration, self.copies, self.keys = calibration, int(copies), int(keys)
        self.capture = self.device.type == "cuda" if capture is None else bool(capture)
        self.captures = self.replays = self.returns = 0
        self._kept: OrderedDict[tuple, _Kept] = OrderedDict()
        self.failure: str | None = None
        self._key: tuple | None = None
        self._static: _Static | None = None
        # the key's graphs and each one's outputs, replayed in turn
        self._graphs: list[torch.cuda.CUDAGraph] = []
        self._outs: list[tuple[dict, torch.Tensor, dict]] = []
        self._warm = 0
        self._stream = torch.cuda.Stream(self.device) if self.capture else None

    def __call__(self, batch: RayBatch) -> tuple[dict, torch.Tensor, dict]:
        """One training step on `batch`. Returns (out, loss, parts) as the device path's
        `_forward` + update would, but with every tensor value a copy that later steps leave
        alone: out holds "n_samples" (and "n_marched") only."""
        cal = () if self.calibration is None else self.calibration.graph_key()
        key = (batch_key(batch), self.field.graph_key(), cal)
        if key != self._key:
            kept = self._kept.pop(key, None)  # before the current key's go aside
            if self._key is None or key[0] != self._key[0]:
                self._static = None  # another batch shape: new buffers, no graph reads them
                self.drop()
                kept = None
            else:
                self._put_aside()
            self._key = key
            if kept is not None:
                self._take_back(kept)
        if self._static is None:
            self._static = _Static.like(batch)
        static = self._static.fill(batch)
        self.field.train_jitter = self._static.jitter
        try:
            return self._snapshot(*self._run(static))
        finally:
            self.field.train_jitter = None

    def _run(self, static: RayBatch) -> tuple[dict, torch.Tensor, dict]:
        if not self._graphs:
            if not self.capture or self._warm < WARMUP:
                self._warm += 1
                return self._eager(static)
            try:  # a capture runs nothing: this step's update is the first replay below
                for _ in range(self.copies):
                    self._capture(static)
            except RuntimeError as e:  # a capture the driver or torch refused: run eagerly
                self.give_up(e)
                return self._eager(static)
        i = self.replays % len(self._graphs)
        self._graphs[i].replay()
        self.replays += 1
        return self._outs[i]

    def _eager(self, static: RayBatch) -> tuple[dict, torch.Tensor, dict]:
        if self._stream is None:
            return self.body(static)
        self._stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(self._stream):
            res = self.body(static)
        torch.cuda.current_stream(self.device).wait_stream(self._stream)
        return res

    def _capture(self, static: RayBatch) -> None:
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):
            out = self.body(static)
        self._graphs.append(graph)
        self._outs.append(out)
        self.captures += 1

    @property
    def graph(self) -> torch.cuda.CUDAGraph | None:
        """The key's first graph (None while warming up or eager)."""
        return self._graphs[0] if self._graphs else None

    def capture_copy(self, batch: RayBatch) -> torch.cuda.CUDAGraph:
        """Another graph of the step under the current key, on the same static inputs (its
        own pool, outputs and gradients), for `benchmarks.graph_relaunch`; the steps keep
        replaying their own copies. Needs a captured `graph` (RuntimeError without one)."""
        if not self._graphs or self._static is None:
            raise RuntimeError("capture_copy needs a captured step")
        static = self._static.fill(batch)
        self.field.train_jitter = self._static.jitter
        try:
            copy = torch.cuda.CUDAGraph()
            with torch.cuda.graph(copy, capture_error_mode="thread_local"):
                self.body(static)
        finally:
            self.field.train_jitter = None
        return copy

    def give_up(self, error: BaseException) -> None:
        """Stop capturing for the rest of the run (one warning); steps run eagerly."""
        self.failure = f"{type(error).__name__}: {error}".splitlines()[0]
        self.capture = False
        self.drop()
        release_generator(self.device)
        warnings.warn(f"CUDA-graph step off, eager from here: {self.failure}", stacklevel=3)

    def drop(self) -> None:
        """Forget every graph, kept ones too (and the gradients they own); the next steps
        warm up again."""
        if self._graphs or self._kept:
            for p in self._params():
                p.grad = None
        self._graphs, self._outs, self._kept = [], [], OrderedDict()
        self._warm = 0

    def _put_aside(self) -> None:
        """Keep the current key's graphs (if any, and `keys` > 1) for a return to it; the
        parameters' .grad let go of a graph's gradients either way, so the next key's steps
        make their own rather than add into a graph's (eager steps' are left as they are)."""
        self._warm = 0
        if not self._graphs:
            return
        params = self._params()
        if self.keys > 1 and not self._room_to_keep():
            self._kept.clear()  # their pools go back with their graphs
        elif self.keys > 1:
            grads = [p.grad for p in params]
            self._kept[self._key] = _Kept(self._graphs, self._outs, grads, self.field.graph_state())
            while len(self._kept) > self.keys - 1:
                self._kept.popitem(last=False)
        for p in params:
            p.grad = None
        self._graphs, self._outs = [], []

    def _room_to_keep(self) -> bool:
        """Whether the device has `KEEP_FREE_SHARE` of its memory free (one driver query, at
        a key change only); always off CUDA, where nothing is captured."""
        if self.device.type != "cuda":
            return True
        free, total = torch.cuda.mem_get_info(self.device)
        return free >= KEEP_FREE_SHARE * total

    def _take_back(self, kept: _Kept) -> None:
        """Make a key's kept graphs current again, with their gradients and the field's
        buffers they write (a key not kept warms up and is captured anew)."""
        self._graphs, self._outs = kept.graphs, kept.outs
        for p, g in zip(self._params(), kept.grads, strict=True):
            p.grad = g
        self.field.set_graph_state(kept.field_state)
        self.returns += 1

    def _params(self) -> list[torch.Tensor]:
        extra = [] if self.calibration is None else self.calibration.parameters()
        return [*self.field.parameters(), *extra]

    @staticmethod
    def _snapshot(out: dict, loss: torch.Tensor, parts: dict) -> tuple[dict, torch.Tensor, dict]:
        """Copies of the step's numbers (one stack, one launch) that the next replay keeps."""
        counts = {k: out[k] for k in ("n_samples", "n_marched") if k in out}
        values = [loss, *parts.values(), *counts.values()]
        if not all(torch.is_tensor(v) for v in values):  # exactly sized (eager) counts
            return counts, loss, parts
        row = torch.stack([v.detach().float().reshape(()) for v in values])
        snap = list(row.unbind())
        n = len(parts)
        return (
            dict(zip(counts, snap[1 + n :], strict=True)),
            snap[0],
            dict(zip(parts, snap[1 : 1 + n], strict=True)),
        )
