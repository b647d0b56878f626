"""Progress bars that stay quiet where nobody watches them.

A tqdm bar written into a log file (stderr not a terminal) leaves thousands of partial
lines; `progress_bar` draws only on a terminal, unless asked otherwise.
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm import tqdm


def progress_bar(*, enabled: bool = True, **kwargs: Any) -> tqdm:
    """A tqdm bar (kwargs as tqdm's) drawn only when `enabled` and stderr is a terminal."""
    kwargs.setdefault("dynamic_ncols", True)
    return tqdm(disable=not (enabled and sys.stderr.isatty()), **kwargs)
