"""Background rendering for the window: the GUI thread never waits on the renderer.

A render may take seconds on a CPU, and while training it must also wait for the trainer's
lock (a step can be long); run in the GUI thread either would freeze the window. The worker
renders one requested view at a time and hands the outputs back; the GUI thread keeps
drawing the last finished frame, and owns everything GL (shading and upload happen there).
"""

from __future__ import annotations

import copy
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fastenerf.data.rig import Intrinsics
from fastenerf.render import field_device

from .frame import ViewSettings, render_raw


@dataclass
class Job:
    """One view to render and what it was requested for (echoed back with the result)."""

    c2w: np.ndarray
    intrinsics: Intrinsics
    settings: ViewSettings
    key: Any = None
    scale: float = 1.0
    model: Any = None


@dataclass
class Result:
    job: Job
    raw: dict[str, torch.Tensor] | None
    seconds: float
    error: str | None = None


class RenderWorker:
    """Renders `Job`s on a daemon thread, one at a time, through `render_raw`.

    source: the ViewSource; its `field` and `lock` are read when each job starts (a reloaded
    checkpoint or a paused trainer is picked up by the next job).
    """

    def __init__(self, source):
        self.src = source
        self._cv = threading.Condition()
        self._job: Job | None = None
        self._result: Result | None = None
        self._busy = False
        self._stop = False
        self._thread = threading.Thread(target=self._loop, name="fastenerf-render", daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        """A job is queued or rendering."""
        return self._busy

    @property
    def has_result(self) -> bool:
        """A finished result waits to be taken."""
        return self._result is not None

    def submit(self, job: Job) -> bool:
        """Queue `job` unless one is in flight (False then: try again next frame)."""
        with self._cv:
            if self._busy or self._stop:
                return False
            job.c2w = np.array(job.c2w, np.float64)
            job.settings = copy.deepcopy(job.settings)  # the GUI keeps editing its own
            self._job, self._busy = job, True
            self._cv.notify_all()
            return True

    def take(self) -> Result | None:
        """The finished result, once (None when there is none new)."""
        with self._cv:
            r, self._result = self._result, None
            return r

    def wait_idle(self, timeout: float | None = None) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: not self._busy, timeout)

    def stop(self, timeout: float = 60.0) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._job is not None or self._stop)
                if self._stop:
                    return
                job, self._job = self._job, None
            t = time.perf_counter()
            try:
                f = self.src.field
                raw = render_raw(f, job.c2w, job.intrinsics, job.settings, self.src.lock)
                if field_device(f).type == "cuda":
                    torch.cuda.synchronize()
                res = Result(job, raw, time.perf_counter() - t)
            except Exception:
                err = traceback.format_exc(limit=2).strip().splitlines()[-1]
                res = Result(job, None, time.perf_counter() - t, err)
            with self._cv:
                self._result, self._busy = res, False
                self._cv.notify_all()
