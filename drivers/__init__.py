"""Camera, lamp and rangefinder drivers (installed as ``uwcam.drivers``)."""
