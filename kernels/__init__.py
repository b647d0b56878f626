"""Warp kernels (installed as `fastenerf.kernels`): each file one concern, forward and backward.

Every op is exposed to PyTorch as a `torch.autograd.Function`; tensors cross zero-copy via
`wp.from_torch`. Kernels run on Warp's CPU backend in tests and on CUDA in benchmarks.
"""
