"""A vehicle surveying a varied seabed, rendered fast enough to stream (scene ``survey``).

The seabed is a periodic height map with reflectance, built once from a seed: a gently
sloping, undulating sandy bottom with ripples, sandstone rocks, a brick partly buried,
a pipe across the track with sand banked against it, a docking ring and a ball. The camera
looks straight down from a vehicle moving along the track at constant speed while its
altitude rises and falls slowly; the lamp rides on the vehicle beside the camera, and the
calibration patch with its ArUco marker sits on a bracket in view, fixed in the image.

Each frame follows the same physics as :func:`uwcam.simulation.render` (Jaffe–McGlamery):

* every pixel's ray is intersected with the height map by Newton steps on
  g(z) = D(X0 + z·px, Y0 + z·py) − Z0 − z (D the seabed depth, (px, py) the pixel's
  normalised image coordinates, z the camera-frame depth), starting from the smooth base
  under the vehicle; the normal comes from the height map's gradient;
* surface light: I_k · ρ_k · beam(θ) · (r/(d_s + r))² · cos γ / π · exp(−c_k d_s) ·
  exp(−G_k d_c), which is the direct term exp(−c_k d_c) plus the forward-scattered term
  exp(−G_k d_c) − exp(−c_k d_c), here unblurred (the forward blur spans about 2 pixels at
  3 m in Jerlov water and conserves light on smooth surfaces);
* backscatter: the slab model's integral along each ray up to the surface, tabulated once
  (the lamp rides with the camera, so the water column in front of it never changes) on a
  coarse pixel grid against log depth, and interpolated per pixel;
* camera: fixed exposure, gain map, dark current, shot and read noise (normal deviates from a
  pool drawn once with the static scenes' counter-based generator, two independent runs of it
  summed per block of pixels: see ``_expose``), quantisation and saturation.

Geometry and light are computed on a grid of every ``step``-th pixel (4: the height map's
1 cm cells span 3 pixels at 4 m) and interpolated bilinearly to the full image, where
exposure and noise are per pixel: a 1280×720 frame costs about 11 ms of rendering and a few ms
of noise on one core (``bench/bench_simulator.py``). Each kernel has a numpy twin, used
where numba is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics
from uwcam.compute.jit import HAVE_NUMBA
from uwcam.simulation.camera import CameraModel, frame_key
from uwcam.simulation.render import PORT_DISTANCE, Ambient, Lamp, KERNELS, slab_edges
from uwcam.simulation.scene import (
    MARKER_CENTRE_M,
    MARKER_ID,
    MARKER_SIDE_M,
    PATCH_CENTRE_M,
    PATCH_DISTANCE_M,
    PATCH_SIZE_M,
    Plane,
    Scene,
    marker_plate,
)
from uwcam.simulation.water import Water

if HAVE_NUMBA:
    from numba import uint64
else:  # pragma: no cover
    uint64 = np.uint64

from uwcam.simulation.survey_kernels import (
    BACKSCATTER_FAR_M,
    BACKSCATTER_NODE_PX,
    BACKSCATTER_SLABS,
    MIN_DEPTH_M,
    _expose,
    _node_backscatter,
    _shade,
    expose_numpy,
    node_backscatter_numpy,
    noise_pool,
    shade_numpy,
    upsample,
)
from uwcam.simulation.terrain import SurveyMotion, Terrain, _base_depth, build_terrain

def bracket_scene() -> Scene:
    """The calibration patch and its ArUco marker on a bracket, in the camera frame (as in the
    ``seabed-patch`` scene, without the seabed)."""
    x, y, d, half = PATCH_CENTRE_M[0], PATCH_CENTRE_M[1], PATCH_DISTANCE_M, PATCH_SIZE_M / 2
    patch = Plane((x, y, d), (0.0, 0.0, -1.0), "grey", half_size=(half, half))
    return Scene("bracket", (patch, marker_plate(MARKER_CENTRE_M, MARKER_SIDE_M, d, MARKER_ID)), textured=())


@dataclass
class SurveyWorld:
    """A vehicle surveying the seabed: frames and ground truth at any time t (s) of the survey."""

    size: tuple[int, int] = (1280, 720)
    fov_deg: float = 60.0
    channel_names: tuple[str, ...] = ("R", "G", "B")
    wavelengths_nm: tuple[float, ...] = (675.0, 575.0, 475.0)
    water: Water | None = None
    lamp: Lamp = field(default_factory=lambda: Lamp(position=(0.1, -0.4, 0.0)))
    camera: CameraModel = field(default_factory=CameraModel)
    motion: SurveyMotion = field(default_factory=SurveyMotion)
    ambient: Ambient | None = None
    seed: int = 0
    material: str | None = None
    bracket: bool = True
    """The calibration patch and its marker on a bracket in view."""
    step: int = 4
    """Geometry and light every this many pixels, interpolated between (the height map's 1 cm
    cells span 3 pixels at 4 m altitude, 7 at 1.5 m)."""
    terrain: Terrain | None = None
    """None: :func:`build_terrain` from the seed."""
    use_numba: bool = HAVE_NUMBA

    def __post_init__(self) -> None:
        from uwcam.simulation.water import water_preset

        w, h = self.size
        if w < 2 or h < 2:
            raise UserInputError(f"image size must be at least 2×2 pixels, got {w}×{h}")
        if self.step < 1:
            raise UserInputError("the shading step must be a whole number of pixels ≥ 1")
        if self.water is None:
            self.water = water_preset("jerlov-II", list(self.wavelengths_nm))
        n = len(self.channel_names)
        if self.terrain is None:
            self.terrain = build_terrain(self.seed, list(self.channel_names), list(self.wavelengths_nm), self.material)
        self.intrinsics = Intrinsics.from_fov(w, h, self.fov_deg)
        intr, s = self.intrinsics, self.step
        self.grid_size = (-(-w // s), -(-h // s))
        ws, hs = self.grid_size
        # Shading point j sits at the centre of pixel block j: x = j·s + (s − 1)/2.
        self._px = (np.arange(ws) * s + 0.5 * (s - 1) - intr.cx) / intr.fx
        self._py = (np.arange(hs) * s + 0.5 * (s - 1) - intr.cy) / intr.fy
        self._foreground(n)
        self._backscatter_table(n)
        self._gain = self.camera.gain_map((h, w, n)).astype(np.float32)
        self._exposure: float | None = None

    def _bracket_hits(self, qx: NDArray, qy: NDArray, n: int) -> tuple[NDArray, NDArray, NDArray]:
        """Range (≤ 0 where none), normal and reflectance of the bracket along the rays of normalised
        image points (qx, qy)."""
        qx, qy = np.broadcast_arrays(qx, qy)
        if not self.bracket:
            return np.full(qx.shape, -1.0), np.zeros((*qx.shape, 3)), np.zeros((*qx.shape, n))
        rays = np.stack([qx, qy, np.ones(qx.shape)], axis=-1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        scene = bracket_scene()
        hit = scene.trace(rays)
        refl = scene.reflectance(hit, rays, list(self.channel_names), list(self.wavelengths_nm))
        rng = np.where(np.isfinite(hit.range), hit.range, -1.0)
        return np.ascontiguousarray(rng), np.ascontiguousarray(hit.normal, dtype=np.float64), np.ascontiguousarray(refl)

    def _foreground(self, n: int) -> None:
        """The bracket on the shading grid; where its marker plate is (not metered for exposure)."""
        self._fg_range, self._fg_normal, self._fg_refl = self._bracket_hits(self._px[None, :], self._py[:, None], n)
        patch_half = PATCH_SIZE_M / 2 / PATCH_DISTANCE_M
        in_patch = ((np.abs(self._px[None, :] - PATCH_CENTRE_M[0] / PATCH_DISTANCE_M) <= patch_half)
                    & (np.abs(self._py[:, None] - PATCH_CENTRE_M[1] / PATCH_DISTANCE_M) <= patch_half))
        self._marker_plate = (self._fg_range > 0) & ~in_patch

    def _backscatter_table(self, n: int) -> None:
        """Cumulative backscatter (relative radiance) along the rays of a coarse pixel grid, at
        log-spaced depths from the port: (gh, gw, levels, N). The slab integrand is the static
        renderer's; its forward-scattered part arrives unblurred (exp(−G t) in all). Per frame
        each node's ray is followed to its own surface and the results interpolated between
        nodes (backscatter varies slowly across the image)."""
        from uwcam.simulation.render import slab_contributions_numpy

        w, h = self.size
        node = BACKSCATTER_NODE_PX
        gh, gw = -(-(h - 1) // node) + 1, -(-(w - 1) // node) + 1
        edges = slab_edges(PORT_DISTANCE, BACKSCATTER_FAR_M, BACKSCATTER_SLABS)
        direct = np.zeros((gh, gw, BACKSCATTER_SLABS, n))
        forward = np.zeros_like(direct)
        water, lamp, intr = self.water, self.lamp, self.intrinsics
        kernel = KERNELS["slab_contributions"] if self.use_numba else slab_contributions_numpy
        kernel(np.array([1.0 / intr.fx, 1.0 / intr.fy]), np.array([intr.cx, intr.cy, h, w], dtype=np.float64), node,
               edges, np.asarray(lamp.position, dtype=np.float64), lamp.effective_radius, lamp.beam_scale,
               lamp.intensities(n), water.attenuation, water.scatter_attenuation, water.backscatter, direct, forward)
        table = np.zeros((gh, gw, BACKSCATTER_SLABS + 1, n))
        table[:, :, 1:] = np.cumsum(direct + forward, axis=2)
        self._table = table
        self._log_z0 = math.log(edges[0])
        self._inv_dlog = BACKSCATTER_SLABS / (math.log(edges[-1]) - math.log(edges[0]))
        # The node rays (as _slab_contributions samples them) and where the bracket cuts them short.
        self._nqx = (np.minimum(np.arange(gw) * node, w - 1) - intr.cx) / intr.fx
        self._nqy = (np.minimum(np.arange(gh) * node, h - 1) - intr.cy) / intr.fy
        fg_range = self._bracket_hits(self._nqx[None, :], self._nqy[:, None], n)[0]
        norm = np.sqrt(self._nqx[None, :] ** 2 + self._nqy[:, None] ** 2 + 1.0)
        self._node_fg_z = np.where(fg_range > 0, fg_range / norm, -1.0)

    # Motion and ground truth ---------------------------------------------------------
    def pose(self, t: float) -> tuple[float, float, float]:
        """Camera position in the world (m): X, Y and depth Z (positive down) at time t (s)."""
        x, y, altitude = self.motion.position(t)
        return x, y, float(_base_depth(x, y)) - altitude

    def axis_range(self, t: float) -> float:
        """Range (m) along the optical axis to the seabed at time t: what a rangefinder looking
        straight down beside the camera measures. On the axis (p = 0) the intersection is exact."""
        x, y, z0 = self.pose(t)
        return float(self.terrain.sample(np.array(x), np.array(y))[0]) - z0

    # Rendering -----------------------------------------------------------------------
    def shade(self, t: float) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
        """Lamp light (at full intensity) and ambient light per channel on the shading grid
        (hs, ws, N) in relative radiance, and the camera range (hs, ws) in m, at time t."""
        ws, hs = self.grid_size
        n = len(self.channel_names)
        x, y, z0 = self.pose(t)
        z_start = max(float(_base_depth(x, y)) - z0, MIN_DEPTH_M)
        lamp_out = np.empty((hs, ws, n), dtype=np.float32)
        amb_out = np.empty((hs, ws, n), dtype=np.float32)
        range_out = np.empty((hs, ws))
        back = np.empty(self._table.shape[:2] + (n,))
        amb = np.zeros(n) if self.ambient is None else np.asarray(self.ambient.irradiance, dtype=np.float64)
        fraction = 0.0 if self.ambient is None else self.ambient.path_fraction
        lamp, water, terrain = self.lamp, self.water, self.terrain
        node_args = (self._nqx, self._nqy, self._node_fg_z, x, y, z0, z_start)
        table_args = (self._table, self._log_z0, self._inv_dlog, back)
        args = (self._fg_range, self._fg_normal, self._fg_refl, np.asarray(lamp.position, dtype=np.float64),
                lamp.effective_radius, lamp.beam_scale, lamp.intensities(n), water.attenuation, water.scatter_attenuation,
                back, float(BACKSCATTER_NODE_PX), float(self.step), amb, fraction, lamp_out, amb_out, range_out)
        if self.use_numba:
            _node_backscatter(*node_args, terrain.padded, terrain.x0, 1.0 / terrain.cell, *table_args)
            _shade(self._px, self._py, x, y, z0, z_start, terrain.padded, terrain.x0, 1.0 / terrain.cell, *args)
        else:
            node_backscatter_numpy(*node_args, terrain, *table_args)
            shade_numpy(self._px, self._py, x, y, z0, z_start, terrain, *args)
        return lamp_out, amb_out, range_out

    def camera_range(self, t: float) -> NDArray[np.float64]:
        """Ground truth (H, W): camera range (m) of every pixel at time t, as rendered."""
        return upsample(self.shade(t)[2][..., None].astype(np.float32), self.size, self.step, self.use_numba)[..., 0].astype(np.float64)

    @property
    def exposure(self) -> float:
        """Electrons per unit radiance: auto-exposure on the lamp-lit view at the start (lowest
        altitude, the brightest seabed), metered on the seabed and the calibration patch but not
        the marker's white plate (which may clip: the marker is still found), then held."""
        if self._exposure is None:
            lamp_rad, amb_rad, _ = self.shade(0.0)
            radiance = lamp_rad.astype(np.float64) + amb_rad
            self._exposure = self.camera.exposure_for(np.where(self._marker_plate[..., None], 0.0, radiance))
        return self._exposure

    def frame(self, t: float, index: int, level: float = 1.0, out: NDArray | None = None,
              exposure_scale: NDArray | None = None) -> NDArray:
        """Frame ``index`` (noise counter) at time t (s) with the lamp at ``level`` (0: off), (H, W, N).
        exposure_scale: (N,) each channel's exposure relative to :attr:`exposure` (None: 1)."""
        w, h = self.size
        n = len(self.channel_names)
        lamp_rad, amb_rad, _ = self.shade(t)
        grid = np.float32(level) * lamp_rad + amb_rad
        if exposure_scale is not None:
            grid = grid * np.asarray(exposure_scale, np.float32)  # (hs, ws, N) × (N,): electrons ∝ exposure time
        radiance = upsample(grid, self.size, self.step, self.use_numba).reshape(-1)
        cam = self.camera
        if out is None:
            out = np.empty((h, w, n), dtype=cam.dtype)
        g = cam.gain_dn_per_e
        kernel = _expose if self.use_numba else expose_numpy
        kernel(radiance, self._gain.reshape(-1), self.exposure, cam.dark_current_e, g, (cam.read_noise_e * g) ** 2,
               frame_key(self.seed * 2 + int(level > 0), index), float(cam.max_code), noise_pool(), out.reshape(-1))
        return out
