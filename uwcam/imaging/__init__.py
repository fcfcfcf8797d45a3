"""Frames in and out: image files and camera response curves (docs/architecture.md)."""
