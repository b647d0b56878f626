"""python blockpy2.py -m MODULE ARGS: run MODULE; a `--set` word `layout=block` is taken out and
sets fastenerf.kernels.composite.CUDA_AUTO = "block" (the composite's block layout as "auto")."""

import runpy
import sys

import fastenerf.kernels.composite as comp

args = sys.argv[1:]
if "layout=block" in args:
    args.remove("layout=block")
    comp.CUDA_AUTO = "block"
    if args and args[-1] == "--set":
        args.pop()
print(f"blockpy2: CUDA_AUTO={comp.CUDA_AUTO}", file=sys.stderr)
assert args[0] == "-m"
sys.argv = [args[1]] + args[2:]
runpy.run_module(args[1], run_name="__main__", alter_sys=True)
