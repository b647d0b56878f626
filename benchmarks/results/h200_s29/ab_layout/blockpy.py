"""python blockpy.py -m MODULE ARGS: run MODULE with the block composite layout as "auto"."""

import runpy
import sys

import fastenerf.kernels.composite as comp

comp.CUDA_AUTO = "block"
assert sys.argv[1] == "-m"
mod = sys.argv[2]
sys.argv = [mod] + sys.argv[3:]
runpy.run_module(mod, run_name="__main__", alter_sys=True)
