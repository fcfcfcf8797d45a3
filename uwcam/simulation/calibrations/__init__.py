"""Simulated-water calibrations that ship with uwcam (see uwcam.runtime.simulated_rig.simulated_calibration)."""
