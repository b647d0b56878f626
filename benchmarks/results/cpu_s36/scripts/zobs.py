"""The row Adam's gate statistic over a CPU run: does it tell settled poses from moving ones?

    python benchmarks/results/cpu_s36/scripts/zobs.py DEG   (DEG 0 or 2; writes ./zDEG.jsonl)

lattice173 (`fastenerf synth --scene lattice --size 173x130 --frames 300` in
/work/scratch/cpu/lattice173), 3000 steps on the CPU, the pose study's prior and refinement.
Every 150 steps (5 % of the budget): over the used rows' turn components, the share whose
z (`pose_refine._gate_factor`: the mean gradient in standard errors) is above 2, its median
and mean, and the rotation error left (0 at 0°: no truth is kept there).
"""

import json
import sys

from fastenerf.config import PerturbConfig, train_preset
from fastenerf.data.formats.native import load_scene
from fastenerf.hooks import Hook, default_hooks
from fastenerf.train import Trainer


class GateZ(Hook):
    def __init__(self, out):
        self.out = out

    def after_step(self, tr, stats):
        if tr.step_count % 150:
            return
        opt, d = tr.selfcal.pose_optimizer, tr.selfcal.poses.delta
        st = opt.state.get(d)
        if not st or "gate_m" not in st:
            return
        b, t = opt.gate_beta, st["row_steps"].clamp_min(1.0)
        bc = 1 - b**t
        var = (st["gate_sq"] / bc) * ((1 - b) * (1 + b**t) / ((1 + b) * bc))
        z = ((st["gate_m"] / bc).abs() / var.clamp_min(1e-30).sqrt())[tr.selfcal.poses.used]
        z = z[:, :3]
        err = float(tr.selfcal.poses.stats().get("pose_error_deg", 0.0))
        row = {"p": tr.step_count / 3000, "frac2": float((z > 2).float().mean())}
        row.update(median=float(z.median()), mean=float(z.mean()), err=err)
        self.out.write(json.dumps(row) + "\n")
        self.out.flush()


def main(deg: float) -> None:
    scene = load_scene("/work/scratch/cpu/lattice173")
    cfg = train_preset(
        "fast", "ngp", steps=3000, device="cpu", refine_poses=True, smooth_poses=121,
        smooth_order=1, eval_every_s=0, checkpoint_every_s=0,
        perturb=PerturbConfig(pose_error_deg=deg),
    )  # fmt: skip
    tr = Trainer(scene, cfg, f"run{deg:g}")
    with open(f"z{deg:g}.jsonl", "w") as f:
        tr.run(hooks=[*default_hooks(tr, False), GateZ(f)], progress=False)


if __name__ == "__main__":
    try:
        level = float(sys.argv[1]) if len(sys.argv) == 2 else float("nan")
    except ValueError:
        level = float("nan")
    if not level >= 0:
        print(
            "zobs.py: error: give one pose error in degrees (0 or more), e.g. zobs.py 2",
            file=sys.stderr,
        )
        sys.exit(2)
    main(level)
