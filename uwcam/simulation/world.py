"""A simulated rig: scene, water, lamp and camera together, with ground truth.

Static scenes render once per lamp state; noisy frames are then cheap (a fixed mean and
standard deviation per pixel plus fresh noise), which is what the simulated camera driver
streams.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics, pixel_rays
from uwcam.calibration.rig import Rig
from uwcam.simulation.camera import CameraModel
from uwcam.simulation.render import Ambient, Components, Lamp, render
from uwcam.simulation.scene import Hit, build_scene
from uwcam.simulation.water import Water, water_preset


@dataclass(frozen=True)
class Channels:
    """Channel names and centre wavelengths (nm) of the simulated camera."""

    names: tuple[str, ...] = ("R", "G", "B")
    wavelengths_nm: tuple[float, ...] = (675.0, 575.0, 475.0)

    def __post_init__(self) -> None:
        if len(self.names) != len(self.wavelengths_nm) or len(self.names) < 2:
            raise UserInputError("the simulated camera needs two or more channels, each with a centre wavelength")


@dataclass
class SimulatedWorld:
    """Everything needed to make frames of one scene. Distances in metres."""

    scene: str = "seabed"
    distance: float = 2.0
    size: tuple[int, int] = (640, 480)
    """Width, height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view."""
    channels: Channels = field(default_factory=Channels)
    water: Water | None = None
    """None: Jerlov II at the channels' wavelengths."""
    lamp: Lamp = field(default_factory=Lamp)
    camera: CameraModel = field(default_factory=CameraModel)
    ambient: Ambient | None = None
    slabs: int = 32
    gate_width: float | None = None
    """Range gating: integrate backscatter only this far in front of the surface (m)."""
    rig: Rig | None = None
    seed: int = 0
    material: str | None = None
    """Give every surface this material (e.g. "sand"), as when calibrating on a piece of the real surface."""
    fixed_exposure: float | None = None
    """Electrons per unit radiance; None: auto-exposure on the lamp-lit scene. Fix it to keep
    several frames radiometrically comparable (absolute attenuation needs that)."""
    exposure_scale: tuple[float, ...] | None = None
    """Each channel's exposure relative to :attr:`exposure` (a 3-chip camera's sensors, exposed
    apart); None: 1 for all. Change it with :meth:`set_exposure_scale`."""

    def __post_init__(self) -> None:
        w, h = self.size
        if w < 2 or h < 2:
            raise UserInputError(f"image size must be at least 2×2 pixels, got {w}×{h}")
        if self.water is None:
            self.water = water_preset("jerlov-II", list(self.channels.wavelengths_nm))
        if len(self.water.attenuation) != len(self.channels.names):
            raise UserInputError("the water has a different number of channels than the camera")
        self.intrinsics = Intrinsics.from_fov(w, h, self.fov_deg)
        self.rays = pixel_rays(self.intrinsics, h, w)
        self._scene = build_scene(self.scene, self.distance, self.rig, self.material)
        self.hit: Hit = self._scene.trace(self.rays)
        self.reflectance = self._scene.reflectance(self.hit, self.rays, list(self.channels.names), list(self.channels.wavelengths_nm))
        self._components: dict[bool, Components] = {}
        self._expected: dict[bool, tuple[NDArray[np.float32], NDArray[np.float32]]] = {}
        self._exposure: float | None = self.fixed_exposure
        if self.exposure_scale is not None:
            self.set_exposure_scale(self.exposure_scale)

    @property
    def camera_range(self) -> NDArray[np.float64]:
        """Ground truth: camera range along each pixel's ray (m), NaN where no surface."""
        return np.where(np.isfinite(self.hit.range), self.hit.range, np.nan)

    @property
    def surface_mask(self) -> NDArray[np.bool_]:
        return np.isfinite(self.hit.range)

    def components(self, lamp_on: bool = True) -> Components:
        """Noise-free image components (relative radiance), rendered once per lamp state."""
        if lamp_on not in self._components:
            lamp = replace(self.lamp, on=lamp_on)
            self._components[lamp_on] = render(self.hit, self.reflectance, self.rays, self.intrinsics, self.water,
                                               lamp, self.ambient, self.slabs, self.gate_width)
        return self._components[lamp_on]

    @property
    def exposure(self) -> float:
        """Electrons per unit radiance, set by auto-exposure on the lamp-lit scene and then held."""
        if self._exposure is None:
            self._exposure = self.camera.exposure_for(self.components(True).total)
        return self._exposure

    def set_exposure_scale(self, scale: tuple[float, ...] | None) -> None:
        """Expose channel k ``scale[k]`` times :attr:`exposure` from the next frame on (None: 1)."""
        if scale is not None and (len(scale) != len(self.channels.names) or not all(np.isfinite(scale)) or min(scale) <= 0):
            raise UserInputError(f"need {len(self.channels.names)} positive exposure factors, got {scale}")
        self.exposure_scale = None if scale is None else tuple(float(v) for v in scale)
        self._expected = {}

    def expected(self, lamp_on: bool = True) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Per-pixel mean and standard deviation in DN (H, W, N)."""
        if lamp_on not in self._expected:
            self._expected[lamp_on] = self.camera.expected(self.components(lamp_on).total, self._channel_exposures())
        return self._expected[lamp_on]

    def _channel_exposures(self) -> float | NDArray[np.float64]:
        """Electrons per unit radiance now, one for all channels or (N,) per channel."""
        return self.exposure if self.exposure_scale is None else self.exposure * np.asarray(self.exposure_scale)

    def frame(self, index: int = 0, lamp_on: bool = True, out: NDArray | None = None) -> NDArray:
        """Frame number ``index`` (H, W, N) as the sensor's integer type; reproducible per seed."""
        mean, std = self.expected(lamp_on)
        return self.camera.digitise(mean, std, self.seed * 2 + int(lamp_on), index, out)

    def noise_free_frame(self, lamp_on: bool = True, backscatter: bool = True) -> NDArray[np.float32]:
        """Expected value in DN (H, W, N), without noise, quantisation or clipping. backscatter=False:
        without the water's own light too, what the surface alone gives the sensor (the truth a
        backscatter compensation aims at)."""
        if backscatter:
            return self.expected(lamp_on)[0]
        parts = self.components(lamp_on)
        return self.camera.expected(parts.total - parts.backscatter, self._channel_exposures())[0]
