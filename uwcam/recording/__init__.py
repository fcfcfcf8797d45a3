"""Recordings: the MCAP layout, the recorder, reading damaged files, and reprocessing (docs/architecture.md)."""
