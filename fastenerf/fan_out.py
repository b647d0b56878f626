"""The hooks of a run trained as one of many (`fastenerf train-many`, the studies).

Such a run is `fastenerf train`'s (periodic evaluation, metrics log, checkpoints, divergence
guard) with a quick evaluation at its end, so every row of a summary has a PSNR, and one
`StopOnSignal` shared by all the runs of a process: after a Ctrl-C the current run
checkpoints and no further run starts.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .evaluate import make_eval_set
from .hooks import Hook, StopOnSignal, default_hooks, evaluate_now

if TYPE_CHECKING:
    from .train import Trainer


class FinalEval(Hook):
    """The quick evaluation (`cfg.eval_views` views at `cfg.eval_scale`) at the end of a run
    that was neither stopped nor failed, as the summary's `last_eval_psnr`. Listed after the
    Checkpointer, it runs before the final checkpoint (hooks end in reverse order), which
    then records the number in progress.json."""

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        scene, c = trainer.scene, trainer.cfg
        if summary["failure"] or summary["interrupted"]:
            return
        if scene.test_c2w is None or not scene.test_rgb_paths:
            return
        ev = make_eval_set(scene, c.eval_views, c.eval_scale)
        summary["last_eval_psnr"] = evaluate_now(trainer, ev)["psnr"]


def fan_out_hooks(trainer: Trainer, stop: StopOnSignal, progress: bool) -> list[Hook]:
    """`default_hooks` with the final evaluation and the process's shared `stop`."""
    hooks = [h for h in default_hooks(trainer, progress) if not isinstance(h, StopOnSignal)]
    return [*hooks, FinalEval(), stop]
