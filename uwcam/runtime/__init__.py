"""The running daemon: devices, the frame loop and its stages, state that survives a restart (docs/architecture.md)."""
