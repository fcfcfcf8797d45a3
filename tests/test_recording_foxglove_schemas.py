"""A recording as Foxglove reads it: every protobuf message decodes with Foxglove's own schema set
(the ``foxglove-schemas-protobuf`` package, not the SDK uwcam writes with), the colour preview is
a CompressedImage Foxglove can draw, and the camera's mounting arrives as a FrameTransform."""

from __future__ import annotations

import importlib
import json
import math

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from tests.test_recording import recording_config, running
from tests.waiting import wait_for
from uwcam.recording import format as rec
from uwcam.config import MountingConfig
from uwcam.recording.format import quaternion_from_rpy_deg

FOXGLOVE_IMAGE_FORMATS = {"jpeg", "png", "webp", "avif"}  # foxglove.CompressedImage's documented formats


def foxglove_class(schema_name: str):
    """The message class of ``foxglove.<Name>`` from Foxglove's published protobuf schemas."""
    assert schema_name.startswith("foxglove."), schema_name
    name = schema_name.split(".", 1)[1]
    return getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)


def rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]) -> np.ndarray:
    """v rotated by the unit quaternion q = (x, y, z, w): q v q*, written out."""
    x, y, z, w = q
    u = np.array([x, y, z])
    v = np.asarray(v, dtype=float)
    return 2 * np.dot(u, v) * u + (w * w - np.dot(u, u)) * v + 2 * w * np.cross(u, v)


@pytest.mark.parametrize(("rpy", "camera_z", "camera_x"), [
    ((-90.0, 0.0, -90.0), (1, 0, 0), (0, -1, 0)),  # forward: optical axis along the bow, image right to starboard
    ((180.0, 0.0, -90.0), (0, 0, -1), (0, -1, 0)),  # down, the top of the image toward the bow
])
def test_mounting_angles_put_the_camera_axes_where_ros_puts_them(rpy, camera_z, camera_x):
    q = quaternion_from_rpy_deg(*rpy)
    assert math.isclose(sum(c * c for c in q), 1.0)
    assert np.allclose(rotate(q, (0, 0, 1)), camera_z, atol=1e-12)
    assert np.allclose(rotate(q, (1, 0, 0)), camera_x, atol=1e-12)


@pytest.mark.slow
def test_every_recorded_message_decodes_with_foxgloves_schemas_and_the_preview_and_transform_are_there(tmp_path):
    path = tmp_path / "dive.mcap"
    cfg = recording_config(tmp_path, start_file=str(path), preview_rate_hz=5.0, results=True)
    cfg.mounting = MountingConfig(translation_m=(0.4, 0.0, -0.2), rotation_deg=(180.0, 0.0, -90.0))
    with running(cfg) as d:
        assert wait_for(lambda: d.recorder.status()["frames_written"] >= 30, 60.0)
        d.recorder.stop()
    counts: dict[str, int] = {}
    previews, transforms, images = [], [], 0
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.message_encoding == "json":
                assert isinstance(json.loads(message.data), dict)
                continue
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            decoded = foxglove_class(schema.name).FromString(message.data)
            assert decoded.SerializeToString() == message.data  # nothing unknown to Foxglove's schema
            if channel.topic == rec.PREVIEW:
                previews.append(decoded)
            elif channel.topic == rec.TRANSFORM:
                transforms.append(decoded)
            elif channel.topic == rec.IMAGE:
                images += 1
    assert {rec.IMAGE, rec.DEPTH, rec.PREVIEW, rec.TRANSFORM, rec.CALIBRATION} <= set(counts)
    # 5 previews a second of 20 frames a second: about one in four frames.
    assert 0.1 * images <= len(previews) <= 0.35 * images + 2
    for preview in previews:
        assert preview.format in FOXGLOVE_IMAGE_FORMATS and preview.frame_id == rec.FRAME_ID
        colour = cv2.imdecode(np.frombuffer(preview.data, np.uint8), cv2.IMREAD_COLOR)
        assert colour.shape == (60, 80, 3) and colour.std() > 1  # half of the 160×120 frames, not blank
    assert transforms and {(t.parent_frame_id, t.child_frame_id) for t in transforms} == {("base_link", rec.FRAME_ID)}
    t = transforms[0]
    assert (t.translation.x, t.translation.y, t.translation.z) == pytest.approx((0.4, 0.0, -0.2))
    q = (t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w)
    assert np.allclose(rotate(q, (0, 0, 1)), (0, 0, -1), atol=1e-9)  # the optical axis points down
