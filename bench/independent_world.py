"""An independent forward model of underwater image formation, written from the physics.

uwcam's own simulator (uwcam/simulation) shares the ranging model's assumptions, so a test on its
frames cannot see what both leave out. This module renders frames from first principles instead and
imports nothing from uwcam.simulation, uwcam.optics, uwcam.water or uwcam.ranging; the only uwcam
thing it reads is the *description of the physical plate* (a rig file, uwcam.calibration.rig), to
know where the plate's grey, black patch and markers are printed.

The world (units in every name; arrays are (H, W) or (H, W, 3), channels R, G, B):

* a pinhole camera W×H (default 160×120) with focal length f px and the principal point at the
  image centre ((W−1)/2, (H−1)/2), looking along +z (x right, y down), in homogeneous water;
* the water per channel k: absorption a_k and scattering b_k (1/m), beam attenuation
  c_k = a_k + b_k, Henyey–Greenstein phase function with asymmetry g (0.9);
* a point lamp at S (default (0.3, 0, 0) m) pointing along +z with a Gaussian beam
  B(θ) = exp(−θ²/(2σ²)) (θ the angle off +z, σ ≈ 30°), radiant intensity I_k (W/sr, arbitrary
  scale): the irradiance normal to the light at a point x at d_s = |x − S| is
  E_k(x) = I_k · B(θ) · exp(−c_k d_s) / d_s²;
* the surface hit by the pixel's ray u (plate, seabed or none) at camera distance d_c = z/u_z,
  Lambertian: L_k = E_k · cos(i) · ρ_k / π · exp(−c_k d_c) (i the lamp's incidence on the surface);
* single-scattering backscatter along the ray from the port (t0 = 0.05 m) to the surface (or
  60 m of open water): L_k^b = ∫ b_k · P_HG(cos ψ) · E_k(t u) · exp(−c_k t) dt, ψ the scattering
  angle between the lamp→point direction and the point→camera direction (−u);
* the camera: cos⁴ vignetting of the ray's angle off the optical axis (optional), an exposure in
  electrons per unit radiance, a fixed per-pixel response (PRNU, 1 % rms, seeded), Poisson shot
  noise (gain in electrons per DN), Gaussian read noise, a dark level and 16-bit clipping.

The noise-free mean is rendered once; :func:`noisy_frame` draws as many frames from it as wanted.
:func:`write_png` writes 16-bit 3-channel PNGs in R, G, B file order (OpenCV's BGR handled here),
which `uwcam calibrate` and `uwcam range` read.

What it leaves out (on purpose, as a different world from uwcam's): forward scattering (no blur, no
plate light spilling into the black patch), multiple scattering, the lamp's finite size, any
spectral width of the channels (each channel is one set of coefficients), lens blur and demosaicing.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

# --- water -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Water:
    """Homogeneous water: per channel (R, G, B) absorption and scattering in 1/m, HG asymmetry g."""

    name: str
    absorption_per_m: tuple[float, float, float]
    scattering_per_m: tuple[float, float, float]
    g: float = 0.9

    @property
    def a(self) -> np.ndarray:
        """Absorption a_k, (3,), 1/m."""
        return np.asarray(self.absorption_per_m, dtype=np.float64)

    @property
    def b(self) -> np.ndarray:
        """Scattering b_k, (3,), 1/m."""
        return np.asarray(self.scattering_per_m, dtype=np.float64)

    @property
    def c(self) -> np.ndarray:
        """Beam attenuation c_k = a_k + b_k, (3,), 1/m."""
        return self.a + self.b


# Where the numbers come from (rounded "like" values, not a fit to one data set; channels taken as
# R ≈ 650 nm, G ≈ 520 nm, B ≈ 470 nm):
# * beam attenuation c: the magnitudes of Jerlov's oceanic water types (Jerlov 1976, "Marine
#   Optics"; Austin & Petzold 1986's revision of the K_d table: type I ≈ 0.03 / 0.06 / 0.35 1/m and
#   type II ≈ 0.06 / 0.09 / 0.39 1/m at 475 / 550 / 650 nm), which are dominated by pure-water
#   absorption in the red (Pope & Fry 1997: a_w ≈ 0.34 1/m at 650 nm, 0.045 at 520, 0.011 at 470);
#   the II-like set is the one the issue (#41) names: c ≈ 0.40 / 0.075 / 0.055 1/m;
# * scattering b: Petzold's (1972) "clear ocean" (Bahamas) b(530 nm) = 0.037 1/m, scaled as λ⁻¹
#   to the other channels for the II-like water (0.030 / 0.038 / 0.042), about half of it for the
#   clearer I-like water; with b a sizeable share of c in green and blue (50–75 %), backscatter
#   matters there as it does in real water;
# * phase function: Henyey–Greenstein with g = 0.9, the usual one-parameter stand-in for Petzold's
#   strongly forward-peaked particle phase functions (Mobley 1994, "Light and Water").
WATERS: dict[str, Water] = {
    "jerlov-I-like": Water("jerlov-I-like", absorption_per_m=(0.345, 0.037, 0.010), scattering_per_m=(0.015, 0.019, 0.021)),
    "jerlov-II-like": Water("jerlov-II-like", absorption_per_m=(0.370, 0.037, 0.013), scattering_per_m=(0.030, 0.038, 0.042)),
}


def henyey_greenstein(cos_psi: np.ndarray, g: float) -> np.ndarray:
    """HG phase function per steradian, normalised so that its integral over 4π sr is 1.

    cos_psi: cosine of the scattering angle (0 = straight on, π = straight back), any shape.
    Returns (1 − g²) / (4π (1 + g² − 2 g cos ψ)^{3/2}), same shape, 1/sr.
    """
    cos_psi = np.asarray(cos_psi, dtype=np.float64)
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * cos_psi) ** 1.5)


# --- lamp --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lamp:
    """A point lamp at ``position_m`` (camera frame, m) pointing along +z.

    sigma_beam_deg: the Gaussian beam's σ in degrees (B(θ) = exp(−θ²/2σ²)); None: an even lamp (B = 1).
    intensity: radiant intensity on the axis per channel (R, G, B), W/sr in an arbitrary common unit.
    """

    position_m: tuple[float, float, float] = (0.3, 0.0, 0.0)
    sigma_beam_deg: float | None = 30.0
    intensity: tuple[float, float, float] = (1.0, 1.0, 1.0)


def lamp_irradiance(points: np.ndarray, lamp: Lamp, water: Water) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lamp's irradiance at ``points`` (..., 3) m, on a surface normal to the light.

    Returns (E, w, d_s): E (..., 3) per channel, I_k·B(θ)·exp(−c_k d_s)/d_s² (lamp units/m²);
    w (..., 3) the unit direction of the light (lamp → point); d_s (...) the distance lamp → point, m.
    """
    v = np.asarray(points, dtype=np.float64) - np.asarray(lamp.position_m, dtype=np.float64)
    d = np.sqrt(np.sum(v * v, axis=-1))
    w = v / d[..., None]
    if lamp.sigma_beam_deg is None:
        beam = np.ones_like(d)
    else:
        theta = np.arccos(np.clip(w[..., 2], -1.0, 1.0))
        beam = np.exp(-(theta**2) / (2.0 * np.radians(lamp.sigma_beam_deg) ** 2))
    intensity = np.asarray(lamp.intensity, dtype=np.float64)
    e = intensity * (beam / (d * d))[..., None] * np.exp(-water.c * d[..., None])
    return e, w, d


# --- camera ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A pinhole camera and its sensor.

    width, height: pixels. focal_px: focal length in pixels (None: a 60° horizontal field of view,
    f = (W/2)/tan 30°). vignetting: multiply by cos⁴ of each ray's angle off the axis.
    prnu: rms of the fixed per-pixel response (1 % default), drawn once from ``prnu_seed``.
    gain_e_per_dn: electrons per DN (shot noise: Var(DN) = mean electrons / gain²).
    read_noise_dn: Gaussian read noise, DN rms. dark_level_dn: the sensor's black level, DN.
    bits: the ADC's depth (values clip to 0 … 2^bits − 1 and are stored as uint16).
    """

    width: int = 160
    height: int = 120
    focal_px: float | None = None
    vignetting: bool = False
    prnu: float = 0.01
    prnu_seed: int = 7
    gain_e_per_dn: float = 1.0
    read_noise_dn: float = 5.0
    dark_level_dn: float = 256.0
    bits: int = 16

    @property
    def f(self) -> float:
        """Focal length, pixels."""
        return float(self.focal_px) if self.focal_px is not None else (self.width / 2.0) / np.tan(np.radians(30.0))

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels, square pixels, principal point at the image centre."""
        return self.f, self.f, (self.width - 1) / 2.0, (self.height - 1) / 2.0

    @property
    def saturation_dn(self) -> int:
        return 2**self.bits - 1


def pixel_rays(camera: Camera) -> np.ndarray:
    """Unit ray u through every pixel centre, (H, W, 3), camera frame (x right, y down, z forward)."""
    fx, fy, cx, cy = camera.intrinsics
    x, y = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    v = np.stack([(x - cx) / fx, (y - cy) / fy, np.ones_like(x)], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def vignetting(camera: Camera) -> np.ndarray:
    """The lens's relative illumination per pixel, (H, W): cos⁴ of the ray's angle off the axis
    (u_z⁴) with ``camera.vignetting``, else 1."""
    if not camera.vignetting:
        return np.ones((camera.height, camera.width))
    return pixel_rays(camera)[..., 2] ** 4


def prnu_map(camera: Camera) -> np.ndarray:
    """Each pixel's relative response per channel, (H, W, 3): 1 + prnu·N(0, 1), the same in every frame."""
    rng = np.random.default_rng(camera.prnu_seed)
    return 1.0 + camera.prnu * rng.standard_normal((camera.height, camera.width, 3))


# --- scene -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlateLayout:
    """What is printed on a plate (plate coordinates: metres from its centre, x right, y down).

    reflectance: (3,) of the plate; black_patch: (centre, size, reflectance (3,)) or None;
    markers: ArUco markers as (bitmap (n, n) of 0/1 with 1 white, centre, side) with their ink and
    white reflectances.
    """

    size_m: tuple[float, float]
    reflectance: tuple[float, float, float]
    black_patch: tuple[tuple[float, float], tuple[float, float], tuple[float, float, float]] | None = None
    markers: tuple = ()
    marker_ink: tuple[float, float, float] = (0.04, 0.04, 0.04)
    marker_white: tuple[float, float, float] = (0.9, 0.9, 0.9)


def plate_from_rig(path: str, wavelengths_nm: tuple[float, float, float] = (650.0, 520.0, 470.0)) -> PlateLayout:
    """The printed layout of a rig file's plate (calibration_rigs/*.yaml), via uwcam.calibration.rig.

    Markers are drawn as OpenCV draws them (cv2.aruco.generateImageMarker, a one-cell black border),
    white cells at the paper's 0.9, as `uwcam rig print` prints them (white paper, the rig's ink).
    """
    from uwcam.calibration.rig import load_rig, resolve_reflectance

    rig = load_rig(path)
    names, wl = ["R", "G", "B"], list(wavelengths_nm)
    plate = rig.plate
    refl = tuple(resolve_reflectance(plate.reflectance, names, wl, "plate"))
    patch = None
    if plate.black_patch is not None:
        bp = plate.black_patch
        patch = (tuple(bp.centre_m), tuple(bp.size_m), tuple(resolve_reflectance(bp.reflectance, names, wl, "black patch")))
    markers, ink = [], (0.04, 0.04, 0.04)
    if plate.markers is not None:
        import cv2

        board = plate.markers
        ink = tuple(resolve_reflectance(board.reflectance, names, wl, "markers"))
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
        cells = dictionary.markerSize + 2
        for m in board.markers:
            bitmap = (cv2.aruco.generateImageMarker(dictionary, m.id, cells) > 127).astype(np.float64)
            markers.append((bitmap, tuple(m.centre_m), board.marker_size_m))
    return PlateLayout(size_m=tuple(plate.size_m), reflectance=refl, black_patch=patch, markers=tuple(markers), marker_ink=ink)


def plate_reflectance(layout: PlateLayout, xp: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """Reflectance (..., 3) at plate coordinates (xp, yp) in m; NaN off the plate."""
    out = np.full(xp.shape + (3,), np.nan)
    w, h = layout.size_m
    on = (np.abs(xp) <= w / 2) & (np.abs(yp) <= h / 2)
    out[on] = layout.reflectance
    if layout.black_patch is not None:
        (px, py), (sw, sh), refl = layout.black_patch
        inside = on & (np.abs(xp - px) <= sw / 2) & (np.abs(yp - py) <= sh / 2)
        out[inside] = refl
    for bitmap, (mx, my), side in layout.markers:
        n = bitmap.shape[0]
        i = np.floor((yp - (my - side / 2)) / side * n).astype(int)
        j = np.floor((xp - (mx - side / 2)) / side * n).astype(int)
        inside = on & (i >= 0) & (i < n) & (j >= 0) & (j < n)
        white = bitmap[np.clip(i, 0, n - 1), np.clip(j, 0, n - 1)] > 0.5
        out[inside & white] = layout.marker_white
        out[inside & ~white] = layout.marker_ink
    return out


@dataclass(frozen=True)
class Scene:
    """What the camera looks at.

    kind: "plate" (a plate of ``layout`` square to the axis, centred on it, at ``distance_m``, open
    water around it), "seabed" (a uniform Lambertian plane of ``reflectance`` square to the axis at
    ``distance_m``, filling the view) or "open-water" (no surface). supersample: sub-pixels per side
    averaged for the plate's printed reflectance (its edges fall between pixels).
    """

    kind: str
    distance_m: float = 1.0
    layout: PlateLayout | None = None
    reflectance: tuple[float, float, float] = (0.18, 0.18, 0.18)
    supersample: int = 4


def surface_map(camera: Camera, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets a surface and its reflectance there.

    Returns (t_hit, rho): t_hit (H, W) the camera→surface distance along the ray in m (inf: no
    surface: open water, or the water beside the plate); rho (H, W, 3) the reflectance (0 where none).
    For a plate the reflectance is the mean over ``supersample``² sub-pixel points of the pixel, and a
    pixel only partly on the plate counts as on it with the plate-part's mean reflectance times its share
    (the water beside it adds no surface light).
    """
    rays = pixel_rays(camera)
    h, w = camera.height, camera.width
    if scene.kind == "open-water":
        return np.full((h, w), np.inf), np.zeros((h, w, 3))
    z = float(scene.distance_m)
    t_hit = z / rays[..., 2]
    if scene.kind == "seabed":
        return t_hit, np.broadcast_to(np.asarray(scene.reflectance, dtype=np.float64), (h, w, 3)).copy()
    if scene.kind != "plate" or scene.layout is None:
        raise ValueError(f"unknown scene {scene.kind!r} (plate needs a layout)")
    fx, fy, cx, cy = camera.intrinsics
    n = max(1, int(scene.supersample))
    offsets = (np.arange(n) + 0.5) / n - 0.5
    x, y = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    total = np.zeros((h, w, 3))
    count = np.zeros((h, w))
    for oy in offsets:
        for ox in offsets:
            r = plate_reflectance(scene.layout, (x + ox - cx) / fx * z, (y + oy - cy) / fy * z)
            on = np.isfinite(r[..., 0])
            total[on] += r[on]
            count += on
    rho = total / (n * n)
    t_hit = np.where(count > 0, t_hit, np.inf)
    return t_hit, rho


def camera_range(camera: Camera, scene: Scene) -> np.ndarray:
    """The true camera range along each pixel's ray to the surface, (H, W), m (NaN where none)."""
    t_hit, _ = surface_map(camera, scene)
    return np.where(np.isfinite(t_hit), t_hit, np.nan)


# --- radiance ----------------------------------------------------------------------------------


def surface_radiance(camera: Camera, scene: Scene, lamp: Lamp, water: Water) -> np.ndarray:
    """The surface's radiance reaching the camera, (H, W, 3) in lamp units/(m²·sr).

    L_k = I_k · B(θ) · exp(−c_k d_s)/d_s² · cos(i) · ρ_k/π · exp(−c_k d_c), with the surface square
    to the axis (normal −z) so cos(i) = (x − S)_z / d_s; 0 where the ray meets no surface.
    """
    rays = pixel_rays(camera)
    t_hit, rho = surface_map(camera, scene)
    hit = np.isfinite(t_hit)
    out = np.zeros(rays.shape)
    if not hit.any():
        return out
    t = t_hit[hit]
    points = rays[hit] * t[:, None]
    e, w, _d = lamp_irradiance(points, lamp, water)
    cos_i = np.clip(w[:, 2], 0.0, 1.0)
    out[hit] = e * cos_i[:, None] * rho[hit] / np.pi * np.exp(-water.c * t[:, None])
    return out


def backscatter_radiance(rays: np.ndarray, t_far: np.ndarray | float, lamp: Lamp, water: Water,
                         t_near: float = 0.05, steps: int = 256, chunk: int = 4096) -> np.ndarray:
    """Single-scattered lamp light along each ray, (..., 3), lamp units/(m²·sr).

    L_k^b = ∫_{t_near}^{t_far} b_k · P_HG(cos ψ) · E_k(t u) · exp(−c_k t) dt, cos ψ = w·(−u)
    (w the lamp → point direction). rays: (..., 3) unit vectors; t_far: (...) or a scalar, m (inf:
    60 m, beyond which nothing of the lamp is left). The integral is the trapezoid rule on ``steps``
    points spaced geometrically from t_near to t_far (fine where the light changes fast, near the port).
    """
    rays = np.asarray(rays, dtype=np.float64)
    shape = rays.shape[:-1]
    u = rays.reshape(-1, 3)
    far = np.broadcast_to(np.asarray(t_far, dtype=np.float64), shape).reshape(-1)
    far = np.where(np.isfinite(far), far, 60.0)
    out = np.zeros((u.shape[0], 3))
    s = np.linspace(0.0, 1.0, steps)
    for a in range(0, u.shape[0], chunk):
        uu, ff = u[a : a + chunk], far[a : a + chunk]
        ok = ff > t_near
        if not ok.any():
            continue
        uu, ff = uu[ok], ff[ok]
        span = np.log(ff / t_near)  # (n,)
        t = t_near * np.exp(span[:, None] * s[None, :])  # (n, steps)
        points = uu[:, None, :] * t[..., None]
        e, w, _d = lamp_irradiance(points, lamp, water)
        cos_psi = -np.sum(w * uu[:, None, :], axis=-1)
        integrand = water.b * henyey_greenstein(cos_psi, water.g)[..., None] * e * np.exp(-water.c * t[..., None])
        integrand *= (t * span[:, None])[..., None]  # dt = t · span · ds
        ds = s[1] - s[0]
        block = ds * (integrand.sum(axis=1) - 0.5 * (integrand[:, 0] + integrand[:, -1]))
        tmp = np.zeros((len(ok), 3))
        tmp[ok] = block
        out[a : a + chunk] = tmp
    return out.reshape(shape + (3,))


def scene_radiance(camera: Camera, scene: Scene, lamp: Lamp, water: Water, backscatter: bool = True,
                   steps: int = 256) -> np.ndarray:
    """Total radiance reaching each pixel, (H, W, 3): the surface's plus (optionally) the water's
    single-scattered light in front of it (to 60 m where there is no surface)."""
    radiance = surface_radiance(camera, scene, lamp, water)
    if backscatter and np.any(water.b > 0):
        t_hit, _ = surface_map(camera, scene)
        radiance = radiance + backscatter_radiance(pixel_rays(camera), t_hit, lamp, water, steps=steps)
    return radiance


# --- sensor ------------------------------------------------------------------------------------


def mean_frame(radiance: np.ndarray, camera: Camera, exposure: float, prnu: bool = True) -> np.ndarray:
    """The noise-free expected raw value per pixel, (H, W, 3) float DN, unclipped.

    DN = dark + exposure · L · V · (1 + PRNU) / gain, with ``exposure`` in electrons per unit radiance
    (the exposure time × aperture × quantum efficiency in one number) and V the vignetting.
    """
    gain = prnu_map(camera) if (prnu and camera.prnu > 0) else 1.0
    electrons = exposure * radiance * vignetting(camera)[..., None] * gain
    return camera.dark_level_dn + electrons / camera.gain_e_per_dn


def auto_exposure(radiance: np.ndarray, camera: Camera, peak_fraction: float = 0.7, percentile: float = 99.9) -> float:
    """The exposure (electrons per unit radiance) that puts the ``percentile`` of the frame's
    noise-free signal above dark at ``peak_fraction`` of the range left above the dark level."""
    signal = mean_frame(radiance, camera, 1.0, prnu=False) - camera.dark_level_dn
    peak = float(np.percentile(signal.max(axis=-1), percentile))
    return peak_fraction * (camera.saturation_dn - camera.dark_level_dn) / peak


def noisy_frame(mean_dn: np.ndarray, camera: Camera, rng: np.random.Generator) -> np.ndarray:
    """One frame drawn from the expected values ``mean_dn`` (H, W, 3): Poisson electrons (shot noise),
    Gaussian read noise, rounded and clipped to 0 … 2^bits − 1, uint16."""
    electrons = np.clip((mean_dn - camera.dark_level_dn) * camera.gain_e_per_dn, 0.0, None)
    dn = rng.poisson(electrons) / camera.gain_e_per_dn + camera.dark_level_dn
    dn = dn + camera.read_noise_dn * rng.standard_normal(mean_dn.shape)
    return np.clip(np.rint(dn), 0, camera.saturation_dn).astype(np.uint16)


def write_png(path: str, frame: np.ndarray) -> None:
    """Write an (H, W, 3) uint16 frame as a 16-bit PNG with the channels in R, G, B order in the
    file (OpenCV writes B, G, R from its array, so the array is flipped first)."""
    import cv2

    if frame.dtype != np.uint16 or frame.ndim != 3 or frame.shape[-1] != 3:
        raise ValueError("write_png writes (H, W, 3) uint16 frames")
    if not cv2.imwrite(str(path), np.ascontiguousarray(frame[..., ::-1])):
        raise OSError(f"OpenCV could not write {path}")


@dataclass
class Rendered:
    """A scene rendered once: its expected raw values and what made them."""

    mean_dn: np.ndarray  # (H, W, 3) float DN
    exposure: float
    truth_m: np.ndarray  # (H, W) camera range, NaN where no surface
    radiance: np.ndarray = field(repr=False)  # (H, W, 3)

    def frames(self, camera: Camera, count: int, seed: int) -> list[np.ndarray]:
        """``count`` independent noisy uint16 frames (seeded)."""
        rng = np.random.default_rng(seed)
        return [noisy_frame(self.mean_dn, camera, rng) for _ in range(count)]


def render(camera: Camera, scene: Scene, lamp: Lamp, water: Water, exposure: float | None = None,
           peak_fraction: float = 0.7, steps: int = 256) -> Rendered:
    """Render ``scene`` once: radiance, the exposure (auto: the frame's bright end at ``peak_fraction``
    of full scale, when None) and the expected raw values."""
    radiance = scene_radiance(camera, scene, lamp, water, steps=steps)
    if exposure is None:
        exposure = auto_exposure(radiance, camera, peak_fraction)
    return Rendered(mean_frame(radiance, camera, exposure), float(exposure), camera_range(camera, scene), radiance)


def with_water(water: Water, **changes) -> Water:
    """A copy of ``water`` with fields replaced (e.g. scattering_per_m=(0, 0, 0))."""
    return replace(water, **changes)
