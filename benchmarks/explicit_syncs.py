"""Who waits for the device on purpose: the explicit synchronisations a few training steps make.

torch's sync debug mode (what `profile_step` counts as host syncs) flags the implicit ones
(`.item()`, a device-to-host copy) but not a call that asks to wait: `torch.cuda.synchronize`,
an event's or stream's `synchronize`, Warp's `wp.synchronize*`. A profile on the H200 showed
the device idle at `cudaDeviceSynchronize` for 0.2-0.4 ms a step with no host sync counted
(issue #17); `ExplicitSyncs` wraps those entry points for a window of steps and records the
first caller outside torch and Warp, so the profile names the line.

    with ExplicitSyncs() as syncs:
        ...                       # the steps
    syncs.calls                   # {"fastenerf/train.py:226 (sync)": 3, ...}
"""

from __future__ import annotations

import functools
import os
import sys
from collections import Counter

import torch

SKIP_DIRS = ("torch", "warp", "contextlib.py", "functools.py")
"""Path parts of frames that are the library's own, not the caller."""


def _caller() -> str:
    """file:line (function) of the first frame outside this module, torch and Warp."""
    f = sys._getframe(2)
    while f is not None:
        path = f.f_code.co_filename
        parts = path.replace("\\", "/").split("/")
        if path != __file__ and not any(p in parts for p in SKIP_DIRS):
            root = os.getcwd()
            short = os.path.relpath(path, root) if path.startswith(root) else path
            return f"{short}:{f.f_lineno} ({f.f_code.co_name})"
        f = f.f_back
    return "unknown"


def _targets() -> list[tuple[object, str]]:
    """(owner, attribute) of every explicit-sync entry point that can be wrapped here."""
    out: list[tuple[object, str]] = [
        (torch.cuda, "synchronize"),
        (torch.cuda.Event, "synchronize"),
        (torch.cuda.Stream, "synchronize"),
    ]
    try:
        import warp as wp
    except ImportError:  # benchmarks of the vanilla backend run without Warp
        return out
    for name in ("synchronize", "synchronize_device", "synchronize_stream", "synchronize_event"):
        if hasattr(wp, name):
            out.append((wp, name))
    return out


class ExplicitSyncs:
    """A context that counts explicit synchronisations by caller (`calls`: Counter of
    "file:line (function)" -> calls); the wrapped functions still synchronise."""

    def __init__(self):
        self.calls: Counter[str] = Counter()
        self._saved: list[tuple[object, str, object]] = []

    def _wrap(self, fn, label: str):
        @functools.wraps(fn)
        def counted(*args, **kwargs):
            self.calls[f"{_caller()} [{label}]"] += 1
            return fn(*args, **kwargs)

        return counted

    def __enter__(self) -> ExplicitSyncs:
        for owner, attr in _targets():
            fn = getattr(owner, attr)
            self._saved.append((owner, attr, fn))
            label = f"{getattr(owner, '__name__', owner)}.{attr}"
            setattr(owner, attr, self._wrap(fn, label))
        return self

    def __exit__(self, *exc) -> None:
        for owner, attr, fn in reversed(self._saved):
            setattr(owner, attr, fn)
        self._saved.clear()

    def per_step(self, steps: int) -> float:
        """Explicit synchronisations per step over `steps` steps."""
        return sum(self.calls.values()) / max(1, steps)

    def examples(self, top: int = 10) -> list[str]:
        """The `top` callers, most calls first: "file:line (function) [entry point] xN"."""
        return [f"{k} x{n}" for k, n in self.calls.most_common(top)]
