"""Camera, lamp and rangefinder drivers (installed as ``uwcam.drivers``).

Drivers are chosen by name through the registry (:mod:`uwcam.drivers.registry`); every
camera runs under :class:`uwcam.drivers.supervisor.SupervisedCamera`.
"""
