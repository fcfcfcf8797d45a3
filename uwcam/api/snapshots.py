"""GET /api/v1/snapshot/…: the latest processed frame as files (range, variance, reasons, image, point cloud)."""

from __future__ import annotations

import io
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.responses import Response

from uwcam.api.common import get_daemon, latest
from uwcam.runtime.daemon import Daemon
from uwcam.optics.geometry import pixel_rays
from uwcam.optics.orientation import normals_from_range

router = APIRouter(prefix="/api/v1/snapshot", tags=["snapshots"])


def range_millimetres(range_m: np.ndarray) -> np.ndarray:
    """Range in metres → little-endian uint16 millimetres, 0 where invalid (1 mm at the least)."""
    return np.where(np.isfinite(range_m), np.clip(np.rint(range_m * 1000.0), 1, 65535), 0).astype("<u2")


def array_response(data: np.ndarray, format: str, headers: dict) -> Response:
    """An array as .npy or TIFF bytes."""
    buf = io.BytesIO()
    if format == "npy":
        np.save(buf, data, allow_pickle=False)
        return Response(buf.getvalue(), media_type="application/octet-stream", headers=headers)
    # Three samples per pixel are stored as RGB only for the colour image; other arrays (normals)
    # as plain samples.
    rgb = data.ndim == 3 and data.shape[2] == 3 and data.dtype.kind == "u"
    import tifffile  # only when a TIFF is read or written: ~2 MB of the daemon's memory
    tifffile.imwrite(buf, data, photometric="rgb" if rgb else "minisblack")
    return Response(buf.getvalue(), media_type="image/tiff", headers=headers)


def false_colour(values: np.ndarray, low: float | None, high: float | None) -> tuple[np.ndarray, float, float]:
    """Metres → BGR false colour (turbo) between low and high; NaN → black. Returns the limits used."""
    finite = values[np.isfinite(values)]
    if low is None:
        low = float(np.percentile(finite, 2)) if finite.size else 0.0
    if high is None:
        high = float(np.percentile(finite, 98)) if finite.size else low + 1.0
    high = max(high, low + 1e-6)
    level = np.clip((np.nan_to_num(values, nan=low) - low) * (255.0 / (high - low)), 0, 255).astype(np.uint8)
    picture = cv2.applyColorMap(level, cv2.COLORMAP_TURBO)
    picture[~np.isfinite(values)] = 0
    return picture, low, high


# Registered before /{kind}, which would otherwise match them first.
@router.get("/normals", responses={200: {"content": {"application/octet-stream": {}, "image/png": {}, "image/tiff": {}}}})
def normals(format: Literal["npy", "tiff", "png"] = Query("npy"), d: Daemon = Depends(get_daemon)) -> Response:
    """Unit surface normals (H, W, 3, float32) of the latest range map in the camera frame (x right,
    y down, z forward), facing the camera, from the range map's gradient; NaN where a pixel or a
    neighbour has no range. png: a picture, (n + 1)/2 as RGB, black where NaN."""
    published = latest(d)
    intr = d.profiles[d.profile_name].camera_intrinsics()
    if intr is None:
        raise HTTPException(status_code=409, detail="normals need camera intrinsics in the calibration profile")
    n = normals_from_range(published.result.range, intr)
    headers = {"X-Frame-Number": str(published.number), "X-Capture-Time": f"{published.frame.wall_time:.6f}"}
    if format == "png":
        rgb = np.clip((np.nan_to_num(n, nan=-1.0) + 1.0) * 127.5, 0, 255).astype(np.uint8)
        return Response(cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes(), media_type="image/png",
                        headers=headers)
    return array_response(n, format, headers)


@router.get("/incidence", responses={200: {"content": {"application/octet-stream": {}, "image/png": {}, "image/tiff": {}}}})
def incidence(format: Literal["npy", "tiff", "png"] = Query("npy"), d: Daemon = Depends(get_daemon)) -> Response:
    """Incidence angle γ (degrees, float32) between the surface normal and the line of sight, one
    per block of pixels (X-Block-Size header; block (i, j) covers rows i·b … i·b + b − 1 and
    columns j·b … j·b + b − 1), from Kirlin's multichannel step (docs/physics.md §9); NaN where no
    angle was found. 409 when orientation is off or unavailable, saying why. png: false colour
    from 0° (blue) to 90°, black where NaN."""
    published = latest(d)
    if published.incidence is None:
        status = d.pipeline.orientation.state if d.pipeline.orientation is not None else \
            "orientation is off (set processing.orientation, e.g. PATCH /api/v1/config {\"orientation\": {}})"
        raise HTTPException(status_code=409, detail=f"no incidence angles: {status}")
    data = published.incidence
    headers = {"X-Frame-Number": str(published.number), "X-Capture-Time": f"{published.frame.wall_time:.6f}",
               "X-Block-Size": str(published.incidence_block)}
    if format == "png":
        picture = false_colour(data, 0.0, 90.0)[0]
        return Response(cv2.imencode(".png", picture)[1].tobytes(), media_type="image/png", headers=headers)
    return array_response(data, format, headers)


@router.get("/pointcloud", responses={200: {"content": {"application/octet-stream": {}}}})
def pointcloud(d: Daemon = Depends(get_daemon)) -> Response:
    """The latest range map as a binary PLY point cloud (camera frame, metres; colour from the image)."""
    published = latest(d)
    profile = d.profiles[d.profile_name]
    intr = profile.camera_intrinsics()
    if intr is None:
        raise HTTPException(status_code=409, detail="a point cloud needs camera intrinsics in the calibration profile")
    r = published.result.range
    rays = pixel_rays(intr, *r.shape)
    normals = normals_from_range(r, intr)
    ok = np.isfinite(r)
    xyz = (r[ok, None] * rays[ok]).astype("<f4")
    nxyz = np.nan_to_num(normals[ok], nan=0.0).astype("<f4")  # 0,0,0 where a neighbour has no range
    img = published.frame.data[ok][:, :3].astype(np.float64)
    peak = float(img.max()) if img.size else 1.0  # a frame may have no valid pixel at all (lamp off)
    rgb = np.clip(img / max(peak, 1.0) * 255.0, 0, 255).astype(np.uint8)
    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                                       ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    vertex["nx"], vertex["ny"], vertex["nz"] = nxyz.T
    vertex["red"], vertex["green"], vertex["blue"] = rgb.T
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"comment uwcam frame {published.number}\nelement vertex {len(vertex)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    return Response(header + vertex.tobytes(), media_type="application/octet-stream",
                    headers={"X-Frame-Number": str(published.number)})


@router.get("/{kind}", responses={200: {"content": {"application/octet-stream": {}, "image/png": {}, "image/tiff": {}}}})
def snapshot(kind: Literal["range", "variance", "reasons", "image", "frames"],
             format: Literal["npy", "tiff", "png16", "png"] = Query("npy"),
             low: Annotated[float | None, Query(ge=0, le=1000, allow_inf_nan=False)] = None,
             high: Annotated[float | None, Query(gt=0, le=1000, allow_inf_nan=False)] = None,
             d: Daemon = Depends(get_daemon)) -> Response:
    """The latest processed frame's range (m), variance (m²), reason codes or colour image, or the
    frames each pixel's range is built from (uint16; 0: no range; 1 everywhere with a range while
    temporal fusion is off).
    png16: range in millimetres as uint16, 0 invalid (data for tools; it looks black in a viewer).
    png: a picture — the colour image (8 or 16 bit), or range / σ (for variance) in false colour
    (turbo, near = blue) between ``low`` and ``high`` metres (default: 2nd and 98th percentile;
    the limits used are in the X-Colour-Limits header), invalid pixels black."""
    if low is not None and high is not None and low >= high:
        raise HTTPException(status_code=422, detail="low must be below high (metres)")
    published = latest(d)
    if kind == "frames":
        data = published.frames if published.frames is not None else np.isfinite(published.result.range).astype(np.uint16)
    else:
        data = {"range": published.result.range, "variance": published.result.variance,
                "reasons": published.result.reasons, "image": published.frame.data}[kind]
    headers = {"X-Frame-Number": str(published.number), "X-Capture-Time": f"{published.frame.wall_time:.6f}"}
    if format in ("npy", "tiff"):
        return array_response(data, format, headers)
    if format == "png16":
        if kind != "range":
            raise HTTPException(status_code=422, detail="png16 is for the range map (millimetres); use npy or tiff")
        mm = range_millimetres(data)
        return Response(cv2.imencode(".png", mm)[1].tobytes(), media_type="image/png", headers=headers)
    if kind in ("reasons", "frames"):
        raise HTTPException(status_code=422, detail=f"png is for pictures of the image, range or σ; use npy or tiff for {kind}")
    if kind != "image":
        values = np.sqrt(data) if kind == "variance" else data
        picture = false_colour(values, low, high)
        headers["X-Colour-Limits"] = f"{picture[1]:.4f},{picture[2]:.4f}"
        return Response(cv2.imencode(".png", picture[0])[1].tobytes(), media_type="image/png", headers=headers)
    bgr = cv2.cvtColor(data[:, :, :3], cv2.COLOR_RGB2BGR)
    return Response(cv2.imencode(".png", bgr)[1].tobytes(), media_type="image/png", headers=headers)
