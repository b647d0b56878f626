"""Does the marched buffer's capacity flap under the tighter defaults (headroom 1.1, shrink
below 0.85)? The device step (fixed-capacity buffers, as the GPU's captured step) on the CPU
for STEPS steps, the capacity's quantum set to QUANTUM slots (the GPU's 32,768 is ~1/9 of
lattice's want; the CPU's batches are smaller), once with the shrink rule as landed (a
shrink saves two quanta or more) and once with the rule before it (any shrink). Every change
of capacity is a change of the captured step's graph key, so a recapture on the GPU.

    PYTHONPATH=. python benchmarks/results/cpu_s40/scripts/flap.py SCENE OUT

Writes OUT/flap.json: per rule, the capacity changes and the capacity after every change (as
quanta).
"""

import json
import os
import sys
from pathlib import Path

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.fields.capacity import SampleCapacity
from fastenerf.hooks import Hook
from fastenerf.train import Trainer

STEPS, QUANTUM = int(os.environ.get("STEPS", "1200")), int(os.environ.get("QUANTUM", "12288"))


class Watch(Hook):
    """The marched buffer's capacity after every step (its quantum set at the first)."""

    def __init__(self):
        self.caps: list[int] = []

    def after_step(self, trainer: Trainer, stats: dict) -> None:
        cap = trainer.field.sampler.sample_capacity
        cap.quantum = QUANTUM
        if cap.capacity is not None and (not self.caps or self.caps[-1] != cap.capacity):
            self.caps.append(cap.capacity)
        if trainer.step_count >= STEPS:
            trainer.request_stop()


def train(scene, out: Path) -> list[int]:
    cfg = train_preset(
        "fast", "ngp", device="cpu", steps=10**6, step_mode="device", rays_per_step=2048
    )
    tr = Trainer(scene, cfg.validate(), out)
    if tr.step_mode != "device":
        raise InputError(f"the device step is not available here ({tr.step_mode})")
    watch = Watch()
    tr.run(hooks=[watch], progress=False)
    return watch.caps


def main(argv: list[str]) -> int:
    if len(argv) != 2 or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("flap.py: error: usage: SCENE (a folder) OUT (new)", file=sys.stderr)
        return 2
    out = Path(argv[1])
    try:
        scene = load_scene_folder(argv[0])
        res = {"steps": STEPS, "quantum": QUANTUM}
        for rule, min_shrink in (("two_quanta", 2), ("any_shrink", 1)):
            SampleCapacity.min_shrink = min_shrink  # 1: any shrink, the rule before 5c2d3ee
            caps = train(scene, out / rule)
            res[rule] = {"changes": len(caps) - 1, "quanta": [c // QUANTUM for c in caps]}
            print(rule, res[rule]["changes"], "changes:", res[rule]["quanta"][:60], flush=True)
        SampleCapacity.min_shrink = 2
        (out / "flap.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError) as e:
        print(f"flap.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
