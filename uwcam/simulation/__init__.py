"""A physically based simulator of underwater image formation.

After Jaffe and McGlamery: a lamp lights a scene of known range and reflectance
through attenuating, scattering water; the camera sees the direct surface light,
its forward-scattered (blurred) part, backscatter from the water column and,
optionally, ambient daylight, then adds realistic sensor noise. The simulated
camera driver, the tests and the benchmarks all use it. Static scenes render once
(:mod:`~uwcam.simulation.world`); the ``survey`` scene, a vehicle moving over a varied
seabed, renders a new view every frame (:mod:`~uwcam.simulation.survey`).
"""

from uwcam.simulation.camera import CameraModel
from uwcam.simulation.render import Ambient, Components, Lamp, render
from uwcam.simulation.scene import SCENES, Scene, build_scene
from uwcam.simulation.water import WATER_PRESETS, Water, water_preset
from uwcam.simulation.world import Channels, SimulatedWorld

__all__ = [
    "SCENES",
    "WATER_PRESETS",
    "Ambient",
    "CameraModel",
    "Channels",
    "Components",
    "Lamp",
    "Scene",
    "SimulatedWorld",
    "Water",
    "build_scene",
    "render",
    "water_preset",
]
