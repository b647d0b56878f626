"""Record what a training march wants, step by step, for replaying the sample buffers'
capacity rules offline (`replay.py`). The fast preset's device step (fixed-capacity buffers, as
the GPU's captured step) on the CPU, 2,048 rays per step, STEPS steps; every step's marched
want (`n_wanted` of the marched buffer, not the compacted one) is kept.

    PYTHONPATH=. python benchmarks/results/cpu_s41/scripts/wants.py SCENE OUT

Writes OUT/wants.json: {"scene", "steps", "rays_per_step", "update_every", "wants": [int per
step]}. The run folder (checkpoints) goes under OUT/run.
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

STEPS, RAYS = int(os.environ.get("STEPS", "2000")), 2048


class Stop(Hook):
    def after_step(self, trainer: Trainer, stats: dict) -> None:
        if trainer.step_count >= STEPS:
            trainer.request_stop()


def record(scene, out: Path) -> dict:
    cfg = train_preset(
        "fast", "ngp", device="cpu", steps=10**6, step_mode="device", rays_per_step=RAYS
    )
    tr = Trainer(scene, cfg.validate(), out / "run")
    if tr.step_mode != "device":
        raise InputError(f"the device step is not available here ({tr.step_mode})")
    sampler, wants, observe = tr.field.sampler, [], SampleCapacity.observe

    def keep(self, n_wanted):
        if self is sampler.sample_capacity:
            wants.append(int(n_wanted))
        observe(self, n_wanted)

    SampleCapacity.observe = keep
    try:
        tr.run(hooks=[Stop()], progress=False)
    finally:
        SampleCapacity.observe = observe
    every = sampler.options.occupancy.update_every
    return {"steps": STEPS, "rays_per_step": RAYS, "update_every": every, "wants": wants}


def main(argv: list[str]) -> int:
    if len(argv) != 2 or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("wants.py: error: usage: SCENE (a folder) OUT (new)", file=sys.stderr)
        return 2
    out = Path(argv[1])
    try:
        res = {"scene": Path(argv[0]).name, **record(load_scene_folder(argv[0]), out)}
        (out / "wants.json").write_text(json.dumps(res))
        w = res["wants"]
        print(res["scene"], len(w), "wants; last 100 mean", sum(w[-100:]) / 100, flush=True)
    except (InputError, OSError) as e:
        print(f"wants.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
