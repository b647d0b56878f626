"""Hash-grid hyper-parameters (DESIGN §4), free of Warp and torch.

Kept apart from `hashgrid.py` so that configuration code (option parsing, `--help`) can read
the encoding's fields, their docstrings and their valid ranges without loading the kernels.
Each field's `metadata` gives its range ("min"/"max" inclusive) for option validation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class HashGridConfig:
    """Hash-grid encoding (instant-ngp); derived per-level layout as properties."""

    n_levels: int = field(default=16, metadata={"min": 1, "max": 32})
    """L, resolution levels (each adds n_features to the encoding's output)."""
    n_features: int = field(default=2, metadata={"choices": (1, 2, 4, 8)})
    """F, features per level and table row."""
    log2_table_size: int = field(default=19, metadata={"min": 10, "max": 24})
    """log2 of T, table rows per hashed level (19: 2^19 rows, 4 MiB per level at F = 2)."""
    base_resolution: int = field(default=16, metadata={"min": 1, "max": 65536})
    """N_min, cells per axis of the coarsest level."""
    max_resolution: int = field(default=2048, metadata={"min": 1, "max": 1 << 20})
    """N_max, cells per axis of the finest level (2048 for a unit-sized box, DESIGN §4)."""
    backward_run: int = field(default=16, metadata={"min": 1, "max": 64})
    """Consecutive points per thread in the table's backward: a ray's samples that share a cell
    add their gradients in registers and reach the table in one reduction per corner (1: a
    thread per point). The same sum either way, up to float rounding order. The default was
    measured on every built-in scene and a mesh scene (benchmarks/RESULTS.md, issue #17)."""

    def __post_init__(self):
        if self.n_levels < 1 or self.n_features not in (1, 2, 4, 8):
            raise ValueError(
                f"HashGridConfig: bad levels/features {self.n_levels}/{self.n_features}"
            )
        if not 1 <= self.log2_table_size <= 30:
            raise ValueError(f"HashGridConfig: log2_table_size {self.log2_table_size} not in 1..30")
        if not 1 <= self.base_resolution <= self.max_resolution:
            raise ValueError("HashGridConfig: need 1 <= base_resolution <= max_resolution")
        if self.backward_run < 1:
            raise ValueError(f"HashGridConfig: backward_run {self.backward_run} < 1")
        if self.n_params * self.n_features >= 2**31:
            raise ValueError("HashGridConfig: table too large for int32 indexing")

    @cached_property
    def table_size(self) -> int:
        return 1 << self.log2_table_size

    @cached_property
    def growth(self) -> float:
        """Per-level scale b."""
        if self.n_levels == 1:
            return 1.0
        return math.exp(
            (math.log(self.max_resolution) - math.log(self.base_resolution)) / (self.n_levels - 1)
        )

    @cached_property
    def resolutions(self) -> tuple[int, ...]:
        """N_l, cells per axis (the 1e-9 guards floor(2047.9999...) at the finest level)."""
        b = self.growth
        return tuple(
            int(math.floor(self.base_resolution * b**lv + 1e-9)) for lv in range(self.n_levels)
        )

    @cached_property
    def hashed(self) -> tuple[bool, ...]:
        return tuple((n + 1) ** 3 > self.table_size for n in self.resolutions)

    @cached_property
    def level_sizes(self) -> tuple[int, ...]:
        """Rows per level: T if hashed, else (N+1)^3 rounded up to a multiple of 8."""
        return tuple(
            self.table_size if h else -(-((n + 1) ** 3) // 8) * 8
            for n, h in zip(self.resolutions, self.hashed, strict=True)
        )

    @cached_property
    def level_offsets(self) -> tuple[int, ...]:
        """First table row of each level, plus the total as the last entry (L + 1 values)."""
        return tuple(int(v) for v in np.concatenate([[0], np.cumsum(self.level_sizes)]))

    @cached_property
    def n_params(self) -> int:
        return self.level_offsets[-1]

    @cached_property
    def n_output_dims(self) -> int:
        return self.n_levels * self.n_features
