"""Calibration: rigs and plates, the fit from frames at known distances, profiles, reports and the guided tank session (docs/architecture.md)."""
