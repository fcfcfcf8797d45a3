"""Simulated-water calibrations that ship with uwcam (see uwcam.daemon.simulated_calibration)."""
