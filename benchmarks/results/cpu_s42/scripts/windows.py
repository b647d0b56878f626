"""Does a plain run with 64 windows per step (the refined run's batch) march and train fewer
samples than the fast preset's 16 at the same PSNR? On the CPU the mesh scene's refined run
with long windows from the start marched 10 % and trained 19 % fewer samples per ray than the
plain run (cpu_s41/samples_toyset173), and the refined run's batch differs from the plain one
mainly in its 64 windows. The fast preset on the CPU, 2,048 rays per step, a STEPS-step
budget, compaction as on the GPU (`early_stop_eps` 1e-4, `compaction_auto`), then the
colour-corrected PSNR on EVAL_VIEWS (8) test views at scale 0.5; SEED (0) the run's seed.

    PYTHONPATH=. python benchmarks/results/cpu_s42/scripts/windows.py SCENE OUT [VARIANT ...]

VARIANT: plain | plain64 | refined_long. Writes OUT/windows.json: per variant the per-16-step
mean marched and trained samples per ray, the wall seconds of training and the PSNR.
"""

import json
import os
import sys
import time
from pathlib import Path

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.evaluate import evaluate_field, make_eval_set
from fastenerf.hooks import Hook
from fastenerf.train import Trainer

STEPS = int(os.environ.get("STEPS", "1500"))
EVAL_VIEWS = int(os.environ.get("EVAL_VIEWS", "8"))
SEED = int(os.environ.get("SEED", "0"))
COMPACTION = {"early_stop_eps": 1e-4, "compaction_auto": True}
VARIANTS = {
    "plain": {},
    "plain64": {"windows_per_step": 64},
    "refined_long": {"refine_poses": True},  # no settle: long field windows from the start
}


class Samples(Hook):
    """Mean marched and trained samples per ray over every 16 steps."""

    def __init__(self):
        self.rows: list[dict] = []
        self._sum = [0.0, 0.0, 0]

    def after_step(self, trainer: Trainer, stats: dict) -> None:
        trained = float(stats.get("samples_per_ray", 0.0))
        s = self._sum
        s[0] += float(stats.get("marched_per_ray", trained))
        s[1] += trained
        s[2] += 1
        if trainer.step_count % 16:
            return
        self.rows.append(
            {"step": trainer.step_count, "marched_per_ray": s[0] / s[2],
             "trained_per_ray": s[1] / s[2]}
        )  # fmt: skip
        self._sum = [0.0, 0.0, 0]


def _tail_mean(rows: list[dict], key: str, frac: float = 0.2) -> float:
    tail = rows[-max(1, int(len(rows) * frac)) :]
    return sum(r[key] for r in tail) / len(tail)


def main(argv: list[str]) -> int:
    names = argv[2:] or list(VARIANTS)
    if len(argv) < 2 or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("windows.py: error: usage: SCENE (a folder) OUT (new) [VARIANT ...]", file=sys.stderr)
        return 2
    if bad := [n for n in names if n not in VARIANTS]:
        print(f"windows.py: error: unknown variant(s) {bad} (known: {list(VARIANTS)})",
              file=sys.stderr)  # fmt: skip
        return 2
    out, res = (
        Path(argv[1]),
        {"steps": STEPS, "eval_views": EVAL_VIEWS, "seed": SEED, "scene": argv[0]},
    )
    try:
        scene = load_scene_folder(argv[0])
        ev = make_eval_set(scene, EVAL_VIEWS, 0.5)
        for name in names:
            cfg = train_preset(
                "fast", "ngp", device="cpu", steps=STEPS, rays_per_step=2048,
                backend_options=COMPACTION, seed=SEED, **VARIANTS[name],
            )  # fmt: skip
            tr = Trainer(scene, cfg.validate(), out / name)
            hook = Samples()
            t = time.perf_counter()
            tr.run(hooks=[hook], progress=False)
            wall = time.perf_counter() - t
            metrics, _ = evaluate_field(tr.field, ev, cfg.chunk)
            res[name] = {
                "psnr": metrics["psnr"], "wall_s": wall,
                "marched_tail": _tail_mean(hook.rows, "marched_per_ray"),
                "trained_tail": _tail_mean(hook.rows, "trained_per_ray"), "rows": hook.rows,
            }  # fmt: skip
            print(name, {k: round(v, 3) for k, v in res[name].items() if k != "rows"}, flush=True)
        (out / "windows.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError) as e:
        print(f"windows.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
