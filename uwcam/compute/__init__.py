"""Compiled kernels' plumbing: numba when installed, a safe threading layer, numpy otherwise (docs/architecture.md)."""
