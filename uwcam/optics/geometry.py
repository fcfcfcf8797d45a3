"""Camera geometry: pixel rays and path length ↔ camera range (docs/physics.md §3).

Camera frame: origin at the camera's centre of projection, x right, y down, z forward
along the optical axis, metres. The lamp sits at S = (Sx, Sy, Sz).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

_AXIS = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels: focal lengths fx, fy and principal point cx, cy."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_fov(cls, width: int, height: int, horizontal_fov_deg: float) -> "Intrinsics":
        """Square pixels, principal point at the image centre, given horizontal field of view."""
        fx = (width / 2.0) / np.tan(np.radians(horizontal_fov_deg) / 2.0)
        return cls(fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)

    def reduced(self, sx: float, sy: float) -> "Intrinsics":
        """The intrinsics of the image reduced ``sx`` times across and ``sy`` times down by area
        averaging: pixel (i, j) of the reduced image is the block centred at full-image pixel
        ((j + 0.5)·sx − 0.5, (i + 0.5)·sy − 0.5)."""
        return Intrinsics(self.fx / sx, self.fy / sy, (self.cx + 0.5) / sx - 0.5, (self.cy + 0.5) / sy - 0.5)


def pixel_rays(intrinsics: Intrinsics, height: int, width: int) -> NDArray[np.float64]:
    """Unit ray u of every pixel centre, shape (height, width, 3)."""
    x = (np.arange(width, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
    y = (np.arange(height, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
    rays = np.empty((height, width, 3))
    rays[..., 0] = x[None, :]
    rays[..., 1] = y[:, None]
    rays[..., 2] = 1.0
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return rays


def camera_range_equidistant(path_length: ArrayLike) -> NDArray[np.float64]:
    """d_c ≈ d_T / 2: lamp beside the camera (m)."""
    return np.asarray(path_length, dtype=np.float64) / 2.0


def _lamp_vector(lamp_position: ArrayLike) -> NDArray[np.float64]:
    s = np.asarray(lamp_position, dtype=np.float64)
    if s.shape != (3,):
        raise ValueError(f"lamp_position must be (x, y, z) in metres, got shape {s.shape}")
    return s


def _lamp_terms(lamp_position: ArrayLike, rays: ArrayLike | None) -> tuple[NDArray, float]:
    s = _lamp_vector(lamp_position)
    u = _AXIS if rays is None else np.asarray(rays, dtype=np.float64)
    return u @ s, float(s @ s)


def camera_range_from_path_length(
    path_length: ArrayLike,
    lamp_position: ArrayLike = (0.0, 0.0, 0.0),
    rays: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Camera range d_c (m) from path length d_T (m), exact for a lamp at S.

    d_c = (d_T² − |S|²) / (2·(d_T − S·u)). rays: (..., 3) unit rays matching
    path_length's shape, or None for the optical axis. Path lengths not longer
    than |S| cannot reach a surface and give NaN.
    """
    d = np.asarray(path_length, dtype=np.float64)
    s_dot_u, s2 = _lamp_terms(lamp_position, rays)
    with np.errstate(all="ignore"):  # unreachable entries are masked below
        reachable = d > np.sqrt(s2)
        return np.where(reachable, (d * d - s2) / (2.0 * (d - s_dot_u)), np.nan)


def camera_range_derivative(
    path_length: ArrayLike,
    lamp_position: ArrayLike = (0.0, 0.0, 0.0),
    rays: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """∂d_c/∂d_T = (d_T² − 2 d_T S·u + |S|²) / (2 (d_T − S·u)²), to carry variances to camera range."""
    d = np.asarray(path_length, dtype=np.float64)
    p, s2 = _lamp_terms(lamp_position, rays)
    with np.errstate(all="ignore"):
        return (d * d - 2.0 * d * p + s2) / (2.0 * (d - p) ** 2)


def path_length_from_camera_range(
    camera_range: ArrayLike,
    lamp_position: ArrayLike = (0.0, 0.0, 0.0),
    rays: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Path length d_T (m) from camera range d_c (m), the forward geometry: d_T = d_c + |d_c·u − S|.

    rays: (..., 3) unit rays matching camera_range's shape, or None for the optical axis.
    """
    s = _lamp_vector(lamp_position)
    dc = np.asarray(camera_range, dtype=np.float64)
    u = _AXIS if rays is None else np.asarray(rays, dtype=np.float64)
    point = dc[..., None] * u
    return dc + np.linalg.norm(point - s, axis=-1)


def plane_camera_range(distance: float, rays: ArrayLike | None = None) -> NDArray[np.float64]:
    """Camera range (m) to a plane square to the optical axis at ``distance`` (m): d / u_z."""
    u = _AXIS if rays is None else np.asarray(rays, dtype=np.float64)
    return distance / u[..., 2]
