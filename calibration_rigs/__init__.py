"""Rig descriptions shipped with uwcam (YAML data files; installed as uwcam.calibration_rigs)."""
