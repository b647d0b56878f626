"""Level weights of an encoding for coarse-to-fine pose refinement (BARF; issue #20).

A field holds optional per-level weights w (hash levels, frequency bands) set by
`fastenerf.coarse_to_fine`. Two ways to apply them:

- `field` (BARF): the features themselves are weighted, so the field sees only the levels
  switched on; it also learns its fine levels late, which costs detail in a short run;
- `gradient`: the field sees every level at full weight and learns them all, and only the
  gradient w.r.t. the positions (the path to the pose corrections) is level-weighted: the
  value is f, its derivative in x is w·∂f/∂x. The pose gradient is as smooth as BARF's while
  the field trains as without the schedule.
"""

from __future__ import annotations

import torch

MODES = ("field", "gradient")


def weight_gradient_only(
    feats_value: torch.Tensor, feats_x: torch.Tensor, w: torch.Tensor
) -> torch.Tensor:
    """Features whose value is `feats_value` and whose gradient w.r.t. the positions is
    w-weighted: feats_value + w·(feats_x − stop_gradient(feats_x)).

    feats_value: (N, C) the features with the gradients to everything but the positions (the
    vanilla field's bands; the hash grid weights its position gradient inside its own backward,
    `hash_grid_encode(x_grad_weights=...)`, one forward instead of two);
    feats_x: (N, C) the same features with the gradient to the positions only (table
    detached); w: (C,) per-column weights in [0, 1].
    """
    return feats_value + w * (feats_x - feats_x.detach())
