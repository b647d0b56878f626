"""Diagnostic, not a product option: the CLI with the ngp colour MLP's view directions cut to
the SH's constant band (a view-independent colour), to test whether view dependence is what
absorbs the prior's slow residual at 2°. Usage: python no_view.py <fastenerf CLI args>."""

import sys

import torch

import fastenerf.fields.ngp as ngp

_sh = ngp.sh_encode


def constant_band(d: torch.Tensor) -> torch.Tensor:
    sh = _sh(d)
    keep = torch.zeros(sh.shape[1], dtype=sh.dtype, device=sh.device)
    keep[0] = 1.0
    return sh * keep


ngp.sh_encode = constant_band

if __name__ == "__main__":
    from fastenerf.cli import main

    sys.exit(main(sys.argv[1:]))
