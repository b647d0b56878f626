"""Benchmarks (DESIGN §8): kernels vs plain PyTorch, error vs time."""
