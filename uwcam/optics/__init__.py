"""Pure optics of colour-attenuation ranging: arrays in, arrays out, no I/O.

Notation follows docs/physics.md: ``signal`` is E_k (dark-corrected, linear), ``attenuation``
is c_k in 1/m, ``path_length`` is d_T = d_s + d_c in metres, ``camera_range`` is d_c.
"""

from uwcam.optics.fusion import fused_path_length
from uwcam.optics.geometry import (
    Intrinsics,
    camera_range_derivative,
    camera_range_equidistant,
    camera_range_from_path_length,
    path_length_from_camera_range,
    pixel_rays,
    plane_camera_range,
)
from uwcam.optics.noise import NoiseModel, signal_variance
from uwcam.optics.reflectance import surface_log_constant, reflectance_ratio_from_range
from uwcam.optics.transform import pair_path_length, pair_path_variance
from uwcam.optics.validity import ChannelState, Reason, channel_states, pixel_reasons

__all__ = [
    "ChannelState",
    "Intrinsics",
    "NoiseModel",
    "Reason",
    "camera_range_derivative",
    "camera_range_equidistant",
    "camera_range_from_path_length",
    "channel_states",
    "fused_path_length",
    "pair_path_length",
    "pair_path_variance",
    "path_length_from_camera_range",
    "pixel_reasons",
    "pixel_rays",
    "plane_camera_range",
    "reflectance_ratio_from_range",
    "signal_variance",
    "surface_log_constant",
]
