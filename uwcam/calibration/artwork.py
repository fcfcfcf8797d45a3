"""Printable artwork of a rig's plate at true scale (PDF, matplotlib): the plate's grey, the
target region's outline, the black patch, the ArUco markers (cv2.aruco) and a 10 cm scale bar."""

from __future__ import annotations

import os

import numpy as np

from uwcam.extras import require_extra
from uwcam.fileio import UserInputError, atomic_write
from uwcam.calibration.rig import Rig

INCH = 0.0254


def _grey(reflectance) -> float:
    """A print grey level for a reflectance (a single value or the mean of a list or spectrum)."""
    if isinstance(reflectance, (int, float)):
        r = float(reflectance)
    elif isinstance(reflectance, list):
        r = float(np.mean(reflectance))
    else:
        r = float(np.mean(reflectance.reflectance))
    # Paper and ink are not linear; this is a starting point; measure the print with a spectrophotometer.
    return float(np.clip(r, 0.0, 1.0) ** (1 / 2.2))


def write_artwork(rig: Rig, path: str | os.PathLike[str], dpi: float = 150.0) -> None:
    """Write the plate at true scale: one PDF page the plate's size (plate coordinates: x right, y down).
    A path ending in .png gets a raster at ``dpi`` instead (for checking the markers by eye or by detector)."""
    import cv2

    matplotlib = require_extra("reports")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    w, h = rig.plate.size_m
    if max(w, h) > 5.0:
        raise UserInputError(f"the plate of rig {rig.name} is {w} × {h} m; artwork is drawn for plates up to 5 m")
    fig = plt.figure(figsize=(w / INCH, h / INCH))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(-w / 2, w / 2)
    ax.set_ylim(h / 2, -h / 2)  # y down, as on the plate
    ax.set_aspect("equal")
    ax.axis("off")
    grey = _grey(rig.plate.reflectance)
    ax.add_patch(Rectangle((-w / 2, -h / 2), w, h, facecolor=(grey,) * 3, edgecolor="none"))
    target = rig.plate.target_area()
    (tx, ty), (tw, th) = target.centre_m, target.size_m
    ax.add_patch(Rectangle((tx - tw / 2, ty - th / 2), tw, th, fill=False, edgecolor=(0.5, 0.5, 0.5), lw=0.5, ls="--"))
    if rig.plate.black_patch is not None:
        bp = rig.plate.black_patch
        g = _grey(bp.reflectance)
        ax.add_patch(Rectangle((bp.centre_m[0] - bp.size_m[0] / 2, bp.centre_m[1] - bp.size_m[1] / 2), *bp.size_m,
                               facecolor=(g,) * 3, edgecolor="none"))
    board = rig.plate.markers
    if board is not None:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
        cells = dictionary.markerSize + 2
        ink = _grey(board.reflectance)
        for m in board.markers:
            image = cv2.aruco.generateImageMarker(dictionary, m.id, cells) / 255.0
            rgb = np.where(image[..., None] > 0.5, 1.0, ink) * np.ones(3)
            s = board.marker_size_m / 2
            ax.imshow(rgb, extent=(m.centre_m[0] - s, m.centre_m[0] + s, m.centre_m[1] + s, m.centre_m[1] - s),
                      interpolation="nearest", zorder=3)  # above the plate's grey
            ax.text(m.centre_m[0], m.centre_m[1] + s * 1.15, str(m.id), ha="center", va="top", fontsize=6, color="0.3")
    ax.set_xlim(-w / 2, w / 2)  # imshow moved the limits
    ax.set_ylim(h / 2, -h / 2)
    # A 10 cm scale bar along the bottom edge, to check the print's scale.
    y = h / 2 - 0.012
    ax.plot([-w / 2 + 0.01, -w / 2 + 0.11], [y, y], color="k", lw=1.5)
    ax.text(-w / 2 + 0.06, y - 0.004, "10 cm", ha="center", va="bottom", fontsize=6)
    ax.text(w / 2 - 0.01, y - 0.004, f"uwcam rig {rig.name}", ha="right", va="bottom", fontsize=6, color="0.3")
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png" if str(path).lower().endswith(".png") else "pdf", dpi=dpi)
    plt.close(fig)
