"""Progress bars that stay quiet in logs.

A tqdm bar redraws itself with carriage returns; written to a file or a pipe (a CI log, `cmd
2> log`) that becomes thousands of partial lines. `progress_bar` is tqdm, disabled when the
caller turns it off or when stderr (where tqdm draws) is not a terminal. Set
`FASTENERF_PROGRESS=1` to draw bars into a non-terminal anyway, `=0` to never draw them.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable


def bars_wanted(enabled: bool = True, stream=None) -> bool:
    """Whether a bar should be drawn: `enabled`, and `stream` (default stderr) is a terminal
    unless FASTENERF_PROGRESS says otherwise."""
    if not enabled:
        return False
    env = os.environ.get("FASTENERF_PROGRESS", "").strip()
    if env in ("0", "1"):
        return env == "1"
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or not a real file
        return False


def progress_bar(iterable: Iterable | None = None, *, enabled: bool = True, **kwargs):
    """`tqdm(iterable, **kwargs)`, disabled unless `bars_wanted(enabled)`; `leave` defaults
    to False (the command prints its own summary line)."""
    from tqdm import tqdm

    kwargs.setdefault("leave", False)
    return tqdm(iterable, disable=not bars_wanted(enabled, kwargs.get("file")), **kwargs)
