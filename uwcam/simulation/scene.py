"""Scenes: analytic surfaces in the camera frame, ray-cast to range, normal and material.

Camera frame: origin at the camera, x right, y down, z forward (metres). The camera
looks straight down at a flat seabed at z = ``distance``; objects sit on the seabed on
the optical axis. Every scene is a list of primitives, each with a material; a pixel
sees the nearest hit along its ray, or open water.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError
from uwcam.calibration.rig import Rig, Spectrum, resolve_reflectance

# Reflectance spectra (sampled 400–700 nm) of the surfaces in the scenes.
_WL = [400.0, 450.0, 500.0, 550.0, 600.0, 650.0, 700.0]
MATERIALS: dict[str, Spectrum] = {
    "sand": Spectrum(wavelength_nm=_WL, reflectance=[0.18, 0.22, 0.27, 0.32, 0.36, 0.39, 0.41]),
    "brick": Spectrum(wavelength_nm=_WL, reflectance=[0.08, 0.08, 0.09, 0.12, 0.25, 0.33, 0.36]),
    "pipe": Spectrum(wavelength_nm=_WL, reflectance=[0.10, 0.12, 0.14, 0.15, 0.15, 0.15, 0.15]),
    "ball": Spectrum(wavelength_nm=_WL, reflectance=[0.10, 0.12, 0.30, 0.62, 0.75, 0.78, 0.80]),
    "ring": Spectrum(wavelength_nm=_WL, reflectance=[0.05, 0.06, 0.12, 0.45, 0.60, 0.62, 0.63]),
    "grey": Spectrum(wavelength_nm=_WL, reflectance=[0.25] * 7),
    "white": Spectrum(wavelength_nm=_WL, reflectance=[0.8] * 7),
    "black": Spectrum(wavelength_nm=_WL, reflectance=[0.03] * 7),
}


@dataclass(frozen=True)
class Hit:
    """Ray-cast result for an image: range (H, W) (inf: open water), normal (H, W, 3), material (H, W)."""

    range: NDArray[np.float64]
    normal: NDArray[np.float64]
    material: NDArray[np.int16]


def _empty(shape: tuple[int, ...]) -> tuple[NDArray, NDArray]:
    return np.full(shape, np.inf), np.zeros((*shape, 3))


@dataclass(frozen=True)
class Plane:
    """Plane through ``point`` with unit ``normal`` facing the camera; optionally a rectangle."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    material: str
    half_size: tuple[float, float] | None = None  # rectangle half-width (x) and half-height (y) about point
    patches: tuple[tuple[tuple[float, float], tuple[float, float], str], ...] = ()  # (centre, size, material)

    def intersect(self, rays: NDArray) -> tuple[NDArray, NDArray, NDArray | None]:
        p, n = np.asarray(self.point), np.asarray(self.normal)
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(denom < -1e-12, (p @ n) / denom, np.inf)
        t = np.where(t > 0, t, np.inf)
        sub = None
        if self.half_size is not None:
            hit = t[..., None] * rays - p
            # In-plane axes: camera x projected on the plane, then normal × that.
            ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
            ex /= np.linalg.norm(ex)
            ey = np.cross(n, ex) * -1.0
            u, v = hit @ ex, hit @ ey
            inside = (np.abs(u) <= self.half_size[0]) & (np.abs(v) <= self.half_size[1])
            t = np.where(inside, t, np.inf)
            sub = np.full(t.shape, -1, dtype=np.int16)
            for k, (centre, size, _) in enumerate(self.patches):
                sub[(np.abs(u - centre[0]) <= size[0] / 2) & (np.abs(v - centre[1]) <= size[1] / 2)] = k
        return t, np.broadcast_to(n, (*t.shape, 3)), sub


def _nearest_positive_root(qa: NDArray, qb: NDArray, qc: NDArray) -> NDArray:
    """The smaller root of qa·t² + qb·t + qc = 0 where it is real and positive, else inf (metres
    along each ray): where a ray from the camera first meets a quadric surface."""
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(disc >= 0, (-qb - np.sqrt(disc)) / (2 * qa), np.inf)
    return np.where(t > 0, t, np.inf)


def _hit_points(t: NDArray, rays: NDArray, centre: NDArray) -> NDArray:
    """Points t·ray relative to ``centre`` (0 where a ray hits nothing), shape (..., 3), metres."""
    return np.where(np.isfinite(t), t, 0.0)[..., None] * rays - centre


@dataclass(frozen=True)
class Sphere:
    """Sphere of ``radius`` (metres) about ``centre`` (metres, camera frame)."""

    centre: tuple[float, float, float]
    radius: float
    material: str

    def intersect(self, rays: NDArray) -> tuple[NDArray, NDArray, None]:
        c = np.asarray(self.centre)
        t = _nearest_positive_root(np.ones(rays.shape[:-1]), -2.0 * (rays @ c), c @ c - self.radius**2)
        normal = _hit_points(t, rays, c) / self.radius
        return t, normal, None


@dataclass(frozen=True)
class Box:
    """Axis-aligned box in a frame rotated by ``yaw_deg`` about the camera z axis.

    ``centre`` in metres, camera frame; ``half_size``: half the edge lengths along the box's own
    x, y and z, metres.
    """

    centre: tuple[float, float, float]
    half_size: tuple[float, float, float]
    yaw_deg: float
    material: str

    def intersect(self, rays: NDArray) -> tuple[NDArray, NDArray, None]:
        a = np.radians(self.yaw_deg)
        rot = np.array([[np.cos(a), np.sin(a), 0.0], [-np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])  # world → box
        d = rays @ rot.T
        o = -(rot @ np.asarray(self.centre))
        h = np.asarray(self.half_size)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - o) / d
            t2 = (h - o) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
        hit = (t_near <= t_far) & (t_near > 0)
        t = np.where(hit, t_near, np.inf)
        axis = np.argmax(np.minimum(t1, t2), axis=-1)
        local = np.zeros((*t.shape, 3))
        np.put_along_axis(local, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], -1)), axis=-1)
        return t, local @ rot, None


@dataclass(frozen=True)
class Cylinder:
    """Finite cylinder (no end caps: its ends lie outside the view or on the seabed).

    ``centre``: the midpoint of its axis, metres, camera frame; ``axis``: a unit vector along it;
    ``radius`` and ``half_length`` (half the length along ``axis``) in metres.
    """

    centre: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float
    half_length: float
    material: str

    def intersect(self, rays: NDArray) -> tuple[NDArray, NDArray, None]:
        c, a = np.asarray(self.centre), np.asarray(self.axis)
        d_perp = rays - (rays @ a)[..., None] * a
        o_perp = -c - (-c @ a) * a
        t = _nearest_positive_root(np.einsum("...i,...i", d_perp, d_perp), 2 * d_perp @ o_perp,
                                   o_perp @ o_perp - self.radius**2)
        point = _hit_points(t, rays, c)
        along = point @ a
        t = np.where(np.abs(along) <= self.half_length, t, np.inf)
        normal = (point - along[..., None] * a) / self.radius
        return t, normal, None


@dataclass(frozen=True)
class Torus:
    """Torus of major radius R and tube radius r about ``axis``, found by sphere tracing.

    ``centre`` in metres, camera frame; ``axis``: the unit normal of the torus's plane; ``major``
    (R, from the centre to the middle of the tube) and ``minor`` (r, the tube's radius) in metres.
    """

    centre: tuple[float, float, float]
    axis: tuple[float, float, float]
    major: float
    minor: float
    material: str

    def _sdf(self, p: NDArray) -> NDArray:
        a = np.asarray(self.axis)
        q = p - np.asarray(self.centre)
        h = q @ a
        radial = np.linalg.norm(q - h[..., None] * a, axis=-1)
        return np.hypot(radial - self.major, h) - self.minor

    def intersect(self, rays: NDArray) -> tuple[NDArray, NDArray, None]:
        t_all, n_all = _empty(rays.shape[:-1])
        c = np.asarray(self.centre)
        bound = Sphere(self.centre, self.major + self.minor, self.material).intersect(rays)[0]
        idx = np.nonzero(np.isfinite(bound))
        if idx[0].size == 0:
            return t_all, n_all, None
        r = rays[idx]
        t = bound[idx].copy()
        far = np.linalg.norm(c) + self.major + self.minor
        done = np.zeros(t.shape, dtype=bool)
        for _ in range(200):
            dist = self._sdf(t[:, None] * r)
            done |= dist < 1e-7
            t = np.where(done, t, t + dist)
            if np.all(done | (t > far)):
                break
        hit = done & (t <= far)
        p = t[:, None] * r
        eps = 1e-6
        p = p[hit]
        grad = np.stack([(self._sdf(p + eps * e) - self._sdf(p - eps * e)) for e in np.eye(3)], axis=-1)
        grad /= np.linalg.norm(grad, axis=-1, keepdims=True)
        t_all[idx] = np.where(hit, t, np.inf)
        hit_rows = tuple(ix[hit] for ix in idx)
        n_all[hit_rows] = grad
        return t_all, n_all, None


Primitive = Plane | Sphere | Box | Cylinder | Torus


@dataclass(frozen=True)
class Scene:
    """A named arrangement of primitives; ``materials`` maps names to reflectance spectra or values."""

    name: str
    primitives: tuple[Primitive, ...]
    materials: dict[str, Spectrum | float | list[float]] = field(default_factory=dict)
    textured: tuple[str, ...] = ("sand",)
    """Materials that get a spectrally flat brightness texture (real seabeds are not uniform)."""

    def material_names(self) -> list[str]:
        names: list[str] = []
        for prim in self.primitives:
            for name in [prim.material, *[p[2] for p in getattr(prim, "patches", ())]]:
                if name not in names:
                    names.append(name)
        return names

    def trace(self, rays: NDArray) -> Hit:
        """Nearest hit of every ray (H, W, 3 unit vectors from the camera)."""
        names = self.material_names()
        best, normal = _empty(rays.shape[:-1])
        material = np.full(best.shape, -1, dtype=np.int16)
        for prim in self.primitives:
            t, n, sub = prim.intersect(rays)
            closer = t < best
            best = np.where(closer, t, best)
            normal = np.where(closer[..., None], n, normal)
            mat = np.full(best.shape, names.index(prim.material), dtype=np.int16)
            if sub is not None:
                for k, patch in enumerate(getattr(prim, "patches", ())):
                    mat[sub == k] = names.index(patch[2])
            material = np.where(closer, mat, material)
        # Normals face the camera.
        flip = np.einsum("...i,...i", normal, rays) > 0
        normal = np.where(flip[..., None], -normal, normal)
        return Hit(best, normal, material)

    def reflectance(self, hit: Hit, rays: NDArray, names: list[str], wavelengths: list[float | None]) -> NDArray[np.float64]:
        """(H, W, N) reflectance per pixel and channel; 0 where no surface."""
        mats = self.material_names()
        out = np.zeros((*hit.range.shape, len(names)))
        for k, mname in enumerate(mats):
            spec = self.materials.get(mname, MATERIALS.get(mname))
            if spec is None:
                raise UserInputError(f"scene {self.name} uses unknown material {mname}")
            out[hit.material == k] = resolve_reflectance(spec, names, wavelengths, f"material {mname}")
        for mname in self.textured:
            if mname in mats:
                sel = hit.material == mats.index(mname)
                point = np.where(np.isfinite(hit.range), hit.range, 0.0)[..., None] * rays
                out[sel] *= _texture(point[sel])[:, None]
        return out


def _texture(points: NDArray) -> NDArray:
    """Brightness texture of a seabed, 1 ± ~0.15, a fixed sum of sinusoids over x and y (metres)."""
    rng = np.random.default_rng(1234)
    value = np.ones(points.shape[0])
    for _ in range(8):
        wavelength = rng.uniform(0.03, 0.4)
        angle = rng.uniform(0, np.pi)
        phase = rng.uniform(0, 2 * np.pi)
        k = 2 * np.pi / wavelength
        value += 0.05 * np.sin(k * (np.cos(angle) * points[:, 0] + np.sin(angle) * points[:, 1]) + phase)
    return value


SCENES: dict[str, str] = {
    "seabed": "flat sandy seabed square to the camera at --range",
    "brick": "a brick (0.215 × 0.1025 m) partly buried in the seabed, 0.10 m proud",
    "pipe": "a 0.26 m diameter pipe lying on the seabed across the view",
    "ball": "an 11 cm ball on sand",
    "ring": "a 0.115 m docking ring (12 mm tube) lying on the seabed",
    "tilted-plane": "a grey plane through the axis at --range, tilted 30° about the x axis",
    "plate": "the calibration plate of a rig (default grey plate) square to the axis at --range, open water behind",
    "open-water": "nothing in range: backscatter (and ambient light) only, for measuring the water's own light",
    "seabed-patch": "the seabed with a grey calibration patch on a bracket 0.8 m in front of the camera, lower right",
}

# The calibration patch of the "seabed-patch" scene, camera frame (m), and the fiducial
# marker (OpenCV ArUco, DICT_4X4_50) beside it that locates it in the image.
PATCH_CENTRE_M = (0.28, 0.18)
PATCH_DISTANCE_M = 0.8
PATCH_SIZE_M = 0.1
MARKER_ID = 7
MARKER_CENTRE_M = (0.15, 0.18)
MARKER_SIDE_M = 0.08


def marker_plate(centre: tuple[float, float], side: float, distance: float, marker_id: int,
                 dictionary: str = "DICT_4X4_50") -> Plane:
    """A white plate with an ArUco marker (black cells, as patches) and a quiet zone around it."""
    import cv2

    cells = 6  # 4×4 bits and a one-cell border
    bits = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)),
                                         marker_id, cells * 10)
    black = cv2.resize(bits, (cells, cells), interpolation=cv2.INTER_AREA) < 128
    cell = side / cells
    patches = tuple(
        ((-side / 2 + (j + 0.5) * cell, -side / 2 + (i + 0.5) * cell), (cell * 1.001, cell * 1.001), "black")
        for i in range(cells) for j in range(cells) if black[i, j]
    )
    half = side * 0.75
    return Plane((centre[0], centre[1], distance), (0.0, 0.0, -1.0), "white", half_size=(half, half), patches=patches)


def marker_cells(dictionary: str, marker_id: int) -> NDArray[np.bool_]:
    """(n, n) True for the black cells of an ArUco marker, its one-cell black border included."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = d.markerSize + 2
    bits = cv2.aruco.generateImageMarker(d, marker_id, cells * 10)
    return cv2.resize(bits, (cells, cells), interpolation=cv2.INTER_AREA) < 128


def marker_patches(dictionary: str, marker_id: int, centre: tuple[float, float], side: float,
                   material: str) -> tuple[tuple[tuple[float, float], tuple[float, float], str], ...]:
    """A marker's black cells as plane patches (centre, size, material), plate coordinates."""
    black = marker_cells(dictionary, marker_id)
    cells = black.shape[0]
    cell = side / cells
    return tuple(
        ((centre[0] - side / 2 + (j + 0.5) * cell, centre[1] - side / 2 + (i + 0.5) * cell), (cell * 1.001, cell * 1.001),
         material)
        for i in range(cells) for j in range(cells) if black[i, j]
    )


def build_scene(name: str, distance: float, rig: Rig | None = None, material: str | None = None) -> Scene:
    """A scene with its seabed (or plate) at camera distance ``distance`` metres along the axis.

    material: give every surface of the scene this material (a name in MATERIALS) instead of
    its own; the plate keeps its rig's reflectances.
    """
    if material is not None and material not in MATERIALS:
        raise UserInputError(f"unknown material '{material}'; known: {', '.join(MATERIALS)}")
    scene = _build_scene(name, distance, rig)
    if material is None or name == "plate":
        return scene
    prims = tuple(replace(p, material=material) for p in scene.primitives)
    return Scene(scene.name, prims, scene.materials, scene.textured)


def _build_scene(name: str, distance: float, rig: Rig | None) -> Scene:
    if not (np.isfinite(distance) and distance > 0):
        raise UserInputError(f"scene range must be a positive number of metres, got {distance}")
    z = float(distance)
    seabed = Plane((0.0, 0.0, z), (0.0, 0.0, -1.0), "sand")
    if name == "seabed":
        return Scene(name, (seabed,))
    if name == "open-water":
        return Scene(name, ())
    if name == "seabed-patch":
        x, y, d, half = PATCH_CENTRE_M[0], PATCH_CENTRE_M[1], PATCH_DISTANCE_M, PATCH_SIZE_M / 2
        patch = Plane((x, y, d), (0.0, 0.0, -1.0), "grey", half_size=(half, half))
        return Scene(name, (seabed, patch, marker_plate(MARKER_CENTRE_M, MARKER_SIDE_M, d, MARKER_ID)), textured=("sand",))
    if name == "brick":
        proud = 0.10
        brick = Box((0.0, 0.0, z - proud / 2), (0.1075, 0.05125, proud / 2), 25.0, "brick")
        return Scene(name, (seabed, brick))
    if name == "pipe":
        r = 0.13
        return Scene(name, (seabed, Cylinder((0.0, 0.0, z - r), (1.0, 0.0, 0.0), r, 3.0, "pipe")))
    if name == "ball":
        r = 0.055
        return Scene(name, (seabed, Sphere((0.0, 0.0, z - r), r, "ball")))
    if name == "ring":
        tube = 0.012
        return Scene(name, (seabed, Torus((0.0, 0.0, z - tube), (0.0, 0.0, 1.0), 0.115 / 2 - tube, tube, "ring")))
    if name == "tilted-plane":
        a = np.radians(30.0)
        return Scene(name, (Plane((0.0, 0.0, z), (0.0, float(np.sin(a)), float(-np.cos(a))), "grey"),), textured=())
    if name == "plate":
        if rig is None:
            from uwcam.calibration.rig import builtin_rig_path, load_rig

            rig = load_rig(builtin_rig_path("grey-plate"))
        patches = ()
        materials: dict[str, Spectrum | float | list[float]] = {"plate": rig.plate.reflectance}
        if rig.plate.black_patch is not None:
            bp = rig.plate.black_patch
            patches = ((bp.centre_m, bp.size_m, "black"),)
            materials["black"] = bp.reflectance
        if rig.plate.markers is not None:
            board = rig.plate.markers
            materials["marker"] = board.reflectance
            for m in board.markers:
                patches += marker_patches(board.dictionary, m.id, m.centre_m, board.marker_size_m, "marker")
        half = (rig.plate.size_m[0] / 2, rig.plate.size_m[1] / 2)
        plate = Plane((0.0, 0.0, z), (0.0, 0.0, -1.0), "plate", half_size=half, patches=patches)
        return Scene(name, (plate,), materials, textured=())
    raise UserInputError(f"unknown scene '{name}'; known scenes: {', '.join(SCENES)}")
