"""Ranging: a frame and a profile in, range, variance and reason maps out (docs/architecture.md)."""
