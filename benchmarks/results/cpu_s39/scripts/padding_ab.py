"""Does a training step's time follow its buffer's slots or its samples? The device step
(fixed-capacity buffers, as the GPU's captured step) on the CPU, after WARMUP steps, with the
marched buffer's capacity held at 1x, 1.5x and 2x what the batches need (same samples, only
padding differs), alternated REPEATS times, STEPS steps each (the step after each change,
which makes the new buffers, is not timed).

    PYTHONPATH=. python benchmarks/results/cpu_s39/scripts/padding_ab.py SCENE OUT [REPEATS]

Writes OUT/padding_ab.json: one row per (factor, repeat): ms/step, slots, samples wanted.
"""

import json
import os
import sys
import time
from pathlib import Path

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.hooks import Hook
from fastenerf.train import Trainer

WARMUP, STEPS = int(os.environ.get("WARMUP", "300")), int(os.environ.get("STEPS", "20"))
FACTORS = (1.0, 1.5, 2.0)


class PaddingAB(Hook):
    """After WARMUP steps: per planned factor, set the capacity, let one step make the
    buffers, then time STEPS steps; stop the run after the last."""

    def __init__(self, repeats: int):
        self.plan = [(r, k) for r in range(repeats) for k in FACTORS]
        self.rows: list[dict] = []
        self.n, self.t0, self.want, self.tight = 0, 0.0, 0, 0

    def after_step(self, trainer: Trainer, stats: dict) -> None:
        self.n += 1
        if self.n < WARMUP:
            return
        cap = trainer.field.sampler.sample_capacity
        seg, at = divmod(self.n - WARMUP, STEPS + 1)
        if self.n == WARMUP:
            cap.shrink_below = 1e-6  # held: never shrinks; grows only past capacity / headroom
            self.want = int(cap._max.item()) if cap._max is not None else 0
            self.want = self.want or int(cap.capacity / cap.headroom)
            self.tight = cap.size_for(self.want)
        if at == 1:
            trainer.sync()
            self.t0 = time.perf_counter()
            return
        if at != 0:
            return
        if seg > 0:
            trainer.sync()
            r, k = self.plan[seg - 1]
            ms = 1e3 * (time.perf_counter() - self.t0) / STEPS
            row = {"factor": k, "repeat": r, "ms_per_step": ms, "slots": cap.capacity}
            self.rows.append({**row, "wanted": self.want})
            print(self.rows[-1], flush=True)
        if seg == len(self.plan):
            trainer.request_stop()
            return
        cap.capacity = cap.quantum * round(self.plan[seg][1] * self.tight / cap.quantum)


def main(argv: list[str]) -> int:
    bad_n = len(argv) == 3 and not (argv[2].isdigit() and int(argv[2]) > 0)
    if len(argv) not in (2, 3) or not Path(argv[0]).is_dir() or Path(argv[1]).exists() or bad_n:
        print(
            "padding_ab.py: error: usage: SCENE (a folder) OUT (new) [REPEATS >= 1]",
            file=sys.stderr,
        )
        return 2
    out, repeats = Path(argv[1]), int(argv[2]) if len(argv) == 3 else 2
    try:
        cfg = train_preset(
            "fast", "ngp", device="cpu", steps=10**6, step_mode="device", rays_per_step=2048
        )
        tr = Trainer(load_scene_folder(argv[0]), cfg.validate(), out / "run")
        if tr.step_mode != "device":
            raise InputError(f"the device step is not available here ({tr.step_mode})")
        ab = PaddingAB(repeats)
        tr.run(hooks=[ab], progress=False)
        (out / "padding_ab.json").write_text(json.dumps(ab.rows, indent=1))
    except (InputError, OSError) as e:
        print(f"padding_ab.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
