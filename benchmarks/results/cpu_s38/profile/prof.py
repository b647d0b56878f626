"""benchmarks.profile_step with every Warp launch wrapped in a record_function("wp::<kernel>")
(so the profiler's self CPU time splits _HashGridEncodeBackward into its table- and x-gradient
kernels), and the top-op list lengthened to 40. Arguments: those of benchmarks.profile_step;
config overrides go through --variant NAME=JSON ({"train": {...}, "backend_options": {...}}).
Run from /work/main: python /work/scratch/s38prof/prof.py --scene ... --variant ..."""

import sys

sys.path.insert(0, "/work/main")
from torch.profiler import record_function  # noqa: E402

import fastenerf.kernels.common as C  # noqa: E402


def _wrap(cls):
    orig = cls.__call__

    def call(self, *a, **k):
        with record_function("wp::" + getattr(self.kernel, "key", str(self.kernel))):
            return orig(self, *a, **k)

    cls.__call__ = call


_wrap(C.Launcher)
if hasattr(C, "TiledLauncher"):
    _wrap(C.TiledLauncher)

import benchmarks.profile_step as P  # noqa: E402

_top = P._top_cpu_ops
P._top_cpu_ops = lambda prof, steps, n=12: _top(prof, steps, 400)
sys.exit(P.main(sys.argv[1:]))
