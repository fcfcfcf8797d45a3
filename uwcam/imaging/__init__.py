"""Frames in and out: image files, camera response curves and the markers found in a frame (docs/architecture.md)."""
