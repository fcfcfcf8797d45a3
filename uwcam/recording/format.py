"""The MCAP layout of a uwcam recording: topics, how frames and results are encoded, and reading
them back. Used by the recorder, the replay camera and ``uwcam reprocess``; see docs/recording.md.

Topics (log time: the frame's capture time, ns since the epoch, so a frame's messages share it):

==========================  ========================  =============================================
``/uwcam/image``            foxglove.RawImage         raw frame at full bit depth (every frame)
``/uwcam/image/preview``    foxglove.CompressedImage  JPEG colour preview for display (``preview_rate_hz``)
``/uwcam/transform``        foxglove.FrameTransform   vehicle → camera (``mounting``), with each status
``/uwcam/image/metadata``   JSON                      sequence, timestamps, exposure, gain, lamp
``/uwcam/depth``            foxglove.RawImage 32FC1   metres along the optical axis, NaN invalid
``/uwcam/variance``         foxglove.RawImage 32FC1   variance of depth, m²
``/uwcam/reasons``          foxglove.RawImage mono8   reason code per pixel (0 valid)
``/uwcam/ranging``          JSON                      per ranged frame: what it was ranged with
``/uwcam/ambient``          foxglove.RawImage 32FCn   ambient light subtracted (when it changes)
``/uwcam/open_water``       foxglove.RawImage 32FCn   open-water frame of the backscatter model (when it changes)
``/uwcam/camera_calibration`` foxglove.CameraCalibration  intrinsics (per file, on change)
``/uwcam/rangefinder``      JSON                      rangefinder readings
``/uwcam/status``           JSON                      daemon status, about once a second
==========================  ========================  =============================================

Attachments: ``profile/<name>.yaml``, every calibration profile the file's frames were ranged with.

Depth follows REP 118: z = range · u_z with u the pixel's unit ray from the profile's intrinsics
(uwcam's range is along each pixel's ray); variance scales by u_z².
"""

from __future__ import annotations

import io
import json
import math
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from uwcam.optics.geometry import pixel_rays
from uwcam.calibration.profile import CalibrationProfile, profile_from_mapping, profile_to_yaml

IMAGE = "/uwcam/image"
IMAGE_METADATA = "/uwcam/image/metadata"
PREVIEW = "/uwcam/image/preview"
TRANSFORM = "/uwcam/transform"
DEPTH = "/uwcam/depth"
VARIANCE = "/uwcam/variance"
REASONS = "/uwcam/reasons"
RANGING = "/uwcam/ranging"
AMBIENT = "/uwcam/ambient"
OPEN_WATER = "/uwcam/open_water"
CALIBRATION = "/uwcam/camera_calibration"
RANGEFINDER = "/uwcam/rangefinder"
STATUS = "/uwcam/status"
FRAME_ID = "uwcam_camera"
PROFILE_PREFIX = "profile/"
PROFILE_MEDIA_TYPE = "application/yaml"


class RecordingError(Exception):
    """A recording cannot be read (not an MCAP file, not a uwcam recording, damaged)."""


def _messages():
    import warnings

    with warnings.catch_warnings():  # foxglove's deprecated alias module warns on import by some paths
        warnings.simplefilter("ignore", DeprecationWarning)
        import foxglove.messages as m
    return m


# ----------------------------------------------------------------------------------- encoding

def image_encoding(data: NDArray) -> str:
    """foxglove.RawImage encoding of an (H, W, C) uint8/uint16 frame: rgb8, mono8, mono16, or the
    OpenCV/ROS type name ``{8|16}UC{C}`` (little-endian, channels in the frame's order)."""
    c = data.shape[-1] if data.ndim == 3 else 1
    bits = data.dtype.itemsize * 8
    if data.dtype == np.uint8 and c == 3:
        return "rgb8"
    if c == 1:
        return "mono8" if bits == 8 else "mono16"
    return f"{bits}UC{c}"


def _decode_encoding(encoding: str) -> tuple[np.dtype, int]:
    named = {"rgb8": ("u1", 3), "mono8": ("u1", 1), "8UC1": ("u1", 1), "mono16": ("<u2", 1), "16UC1": ("<u2", 1),
             "32FC1": ("<f4", 1)}
    if encoding in named:
        dt, c = named[encoding]
        return np.dtype(dt), c
    for prefix, dt in (("8UC", "u1"), ("16UC", "<u2"), ("32FC", "<f4")):
        if encoding.startswith(prefix) and encoding[len(prefix):].isdigit():
            return np.dtype(dt), int(encoding[len(prefix):])
    raise RecordingError(f"unsupported image encoding '{encoding}' in the recording")


def timestamp(ns: int):
    return _messages().Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _varint(n: int) -> bytes:
    """Protobuf base-128 varint; negative numbers as 64-bit two's complement (int64)."""
    n &= (1 << 64) - 1
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _image_layout(data: NDArray) -> tuple[NDArray, int, int, int]:
    """An (H, W[, C]) array as foxglove.RawImage stores it: (C-contiguous little-endian data, H, W,
    bytes per row)."""
    data = np.ascontiguousarray(data)
    if data.dtype.byteorder == ">":
        data = data.astype(data.dtype.newbyteorder("<"))
    h, w = data.shape[:2]
    return data, h, w, w * (data.shape[2] if data.ndim == 3 else 1) * data.dtype.itemsize


def raw_image(data: NDArray, log_time_ns: int, encoding: str | None = None) -> bytes:
    """foxglove.RawImage (protobuf bytes) of an (H, W[, C]) array, little-endian, unpadded.

    Encoded here rather than through the Foxglove SDK's message class, which copies a frame's
    pixels twice byte by byte (16 ms for a 1920×1080×3 16-bit frame against 1 ms here): the bytes
    are the same, field for field (tests/test_recording_encoding.py compares them with the SDK's)."""
    data, h, w, step = _image_layout(data)
    seconds, nanos = divmod(log_time_ns, 1_000_000_000)
    stamp = (b"\x08" + _varint(seconds) if seconds else b"") + (b"\x10" + _varint(nanos) if nanos else b"")
    text = (encoding or image_encoding(data)).encode()
    pixels = memoryview(data.reshape(-1)).cast("B")
    parts: list[bytes | memoryview] = []
    # Field numbers of foxglove.RawImage; proto3 leaves out scalar fields at their default (0,
    # empty), while a message field that is set (the timestamp) is written even when empty.
    parts += [b"\x0a", _varint(len(stamp)), stamp]  # 1 timestamp (google.protobuf.Timestamp)
    for key, value in ((b"\x15", w), (b"\x1d", h)):  # 2 width, 3 height: fixed32
        if value:
            parts += [key, struct.pack("<I", value)]
    if text:
        parts += [b"\x22", _varint(len(text)), text]  # 4 encoding
    if step:
        parts += [b"\x2d", struct.pack("<I", step)]  # 5 step: fixed32
    if len(pixels):
        parts += [b"\x32", _varint(len(pixels)), pixels]  # 6 data
    parts += [b"\x3a", _varint(len(FRAME_ID)), FRAME_ID.encode()]  # 7 frame_id
    return b"".join(parts)


def raw_image_message(data: NDArray, log_time_ns: int, encoding: str | None = None):
    """foxglove.RawImage message of an (H, W[, C]) array, little-endian, unpadded."""
    data, h, w, step = _image_layout(data)
    m = _messages()
    return m.RawImage(timestamp=timestamp(log_time_ns), frame_id=FRAME_ID, width=w, height=h,
                      encoding=encoding or image_encoding(data), step=step, data=data.tobytes())


def decode_raw_image(message: Any) -> NDArray:
    """Array (H, W, C) (C ≥ 2) or (H, W) from a decoded foxglove.RawImage message."""
    dtype, c = _decode_encoding(message.encoding)
    row = message.width * c * dtype.itemsize
    buf = np.frombuffer(message.data, dtype=np.uint8).reshape(message.height, message.step)[:, :row]
    arr = np.ascontiguousarray(buf).view(dtype).reshape(message.height, message.width, c)
    return arr[:, :, 0] if c == 1 else arr


def depth_factor(profile: CalibrationProfile, height: int, width: int) -> NDArray[np.float32]:
    """u_z per pixel (H, W): depth along the optical axis = range along the ray × u_z. Without
    intrinsics in the profile every ray is taken as the optical axis (factor 1)."""
    intr = profile.camera_intrinsics()
    if intr is None:
        return np.ones((height, width), np.float32)
    return pixel_rays(intr, height, width)[..., 2].astype(np.float32)


def camera_calibration(profile: CalibrationProfile, width: int, height: int, log_time_ns: int) -> bytes:
    """foxglove.CameraCalibration (protobuf bytes) of the profile's pinhole intrinsics."""
    return calibration_message(profile, width, height, log_time_ns).encode()


def calibration_message(profile: CalibrationProfile, width: int, height: int, log_time_ns: int):
    """foxglove.CameraCalibration of the profile's pinhole intrinsics (K all zero: uncalibrated)."""
    intr = profile.camera_intrinsics()
    fx, fy, cx, cy = (intr.fx, intr.fy, intr.cx, intr.cy) if intr else (0.0, 0.0, 0.0, 0.0)
    m = _messages()
    return m.CameraCalibration(timestamp=timestamp(log_time_ns), frame_id=FRAME_ID, width=width, height=height,
                               distortion_model="plumb_bob", D=[0.0] * 5, K=[fx, 0, cx, 0, fy, cy, 0, 0, 1],
                               R=[1.0, 0, 0, 0, 1, 0, 0, 0, 1], P=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0])


def compressed_image(data: bytes, log_time_ns: int, image_format: str = "jpeg") -> bytes:
    """foxglove.CompressedImage (protobuf bytes) of an encoded image (``format`` jpeg, png or webp)."""
    m = _messages()
    return m.CompressedImage(timestamp=timestamp(log_time_ns), frame_id=FRAME_ID, data=data,
                             format=image_format).encode()


def quaternion_from_rpy_deg(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the rotation Rz(yaw)·Ry(pitch)·Rx(roll), angles in degrees (ROS's convention)."""
    r, p, y = (math.radians(a) / 2.0 for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def frame_transform(parent_frame: str, translation_m, rotation_deg, log_time_ns: int) -> bytes:
    """foxglove.FrameTransform (protobuf bytes) from ``parent_frame`` (the vehicle) to the camera's frame."""
    m = _messages()
    x, y, z, w = quaternion_from_rpy_deg(*rotation_deg)
    return m.FrameTransform(timestamp=timestamp(log_time_ns), parent_frame_id=parent_frame, child_frame_id=FRAME_ID,
                            translation=m.Vector3(x=float(translation_m[0]), y=float(translation_m[1]),
                                                  z=float(translation_m[2])),
                            rotation=m.Quaternion(x=x, y=y, z=z, w=w)).encode()


def profile_attachment_name(profile: CalibrationProfile) -> str:
    return f"{PROFILE_PREFIX}{profile.name}.yaml"


# ------------------------------------------------------------------------------------ writing

JSON_SCHEMA = json.dumps({"type": "object"}).encode()


class McapFile:
    """One MCAP file being written: channels registered on first use, chunked and indexed."""

    def __init__(self, path: str, chunk_size: int = 1 << 20, replace: bool = False, compression: str = "lz4") -> None:
        """replace: write over an existing file (only for a temporary file of one's own);
        compression: of each chunk, "lz4", "zstd" or "none" (see RecordingConfig.compression)."""
        from mcap.writer import CompressionType, Writer

        kind = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}[compression]
        self.path = path
        self._fh = open(path, "wb" if replace else "xb")  # never over a recording by accident
        try:
            self.writer = Writer(self._fh, chunk_size=chunk_size, compression=kind)
            self.writer.start(profile="", library="uwcam")
        except BaseException:
            self._fh.close()
            raise
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self.messages = 0
        self.payload_bytes = 0
        """Bytes of message data handed to the writer (before chunk compression)."""

    def _schema(self, name: str) -> int:
        if name not in self._schemas:
            if name == "json":
                self._schemas[name] = self.writer.register_schema("uwcam.Json", "jsonschema", JSON_SCHEMA)
            else:
                schema = getattr(_messages(), name.split(".")[-1]).get_schema()
                self._schemas[name] = self.writer.register_schema(schema.name, schema.encoding, schema.data)
        return self._schemas[name]

    def write(self, topic: str, schema: str, data: bytes, log_time_ns: int) -> None:
        """schema: "json" or a Foxglove schema name such as "foxglove.RawImage"."""
        if topic not in self._channels:
            encoding = "json" if schema == "json" else "protobuf"
            self._channels[topic] = self.writer.register_channel(topic, encoding, self._schema(schema))
        self.writer.add_message(self._channels[topic], log_time=log_time_ns, data=data,
                                publish_time=log_time_ns, sequence=self.messages)
        self.messages += 1
        self.payload_bytes += len(data)

    def write_json(self, topic: str, value: dict, log_time_ns: int) -> None:
        self.write(topic, "json", json.dumps(value, default=_json_default).encode(), log_time_ns)

    def attach(self, name: str, media_type: str, data: bytes, log_time_ns: int) -> None:
        self.writer.add_attachment(create_time=log_time_ns, log_time=log_time_ns, name=name,
                                   media_type=media_type, data=data)

    def attach_profile(self, profile: CalibrationProfile, log_time_ns: int) -> None:
        self.attach(profile_attachment_name(profile), PROFILE_MEDIA_TYPE, profile_to_yaml(profile).encode(), log_time_ns)

    def size(self) -> int:
        return self._fh.tell()

    def finish(self) -> None:
        """Write the summary and footer and close."""
        try:
            self.writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
        finally:
            self._fh.close()

    def abandon(self) -> None:
        """Close without writing more (after a write error); :func:`repair` makes the file readable."""
        try:
            self._fh.close()
        except OSError:
            pass  # the buffered tail cannot be written either: repair cuts it off


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


# ------------------------------------------------------------------------------------- repair

_MAGIC = b"\x89MCAP0\r\n"
_OP_DATA_END, _OP_FOOTER = 0x0F, 0x02


def is_complete(path: str) -> bool:
    """True if the file ends with an MCAP footer and magic (finished by its writer)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell() < 2 * len(_MAGIC) + 29:
                return False
            fh.seek(-(len(_MAGIC) + 29), os.SEEK_END)
            tail = fh.read()
    except OSError:
        return False
    return tail[0] == _OP_FOOTER and tail.endswith(_MAGIC)


def repair(path: str) -> int:
    """Make an unfinished recording (killed writer, full disk) readable by any MCAP reader: cut
    it after the last complete record and append a data-end record and a footer (no summary: a
    reader scans the file). Truncating first frees the space the footer needs. Returns the
    number of bytes kept. A complete file is left as it is."""
    if is_complete(path):
        return os.path.getsize(path)
    with open(path, "r+b") as fh:
        head = fh.read(len(_MAGIC))
        if head != _MAGIC:
            raise RecordingError(f"{path} is not an MCAP file")
        good = fh.tell()
        while True:
            header = fh.read(9)
            if len(header) < 9:
                break
            opcode, length = header[0], struct.unpack("<Q", header[1:])[0]
            if opcode in (_OP_DATA_END, _OP_FOOTER):
                break  # an unfinished summary: keep the data before it
            fh.seek(length, os.SEEK_CUR)
            if fh.tell() > os.fstat(fh.fileno()).st_size:
                break  # the record was cut short
            good = fh.tell()
        fh.truncate(good)
        fh.seek(good)
        # DataEnd (data section CRC 0: unknown), Footer (no summary), closing magic.
        fh.write(struct.pack("<BQI", _OP_DATA_END, 4, 0))
        fh.write(struct.pack("<BQQQI", _OP_FOOTER, 20, 0, 0, 0))
        fh.write(_MAGIC)
        fh.flush()
        os.fsync(fh.fileno())
    return good


# ------------------------------------------------------------------------------------ reading

def open_reader(stream: IO[bytes]):
    """A stock ``mcap`` reader that decodes the protobuf (Foxglove) and JSON messages."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    return make_reader(stream, decoder_factories=[DecoderFactory(), _JsonDecoderFactory()])


def open_checked_reader(stream: IO[bytes], skip_offsets: tuple[int, ...] = ()):
    """Like :func:`open_reader`, but never reading a damaged chunk (:mod:`uwcam.recording.chunk_check`)."""
    from mcap_protobuf.decoder import DecoderFactory

    from uwcam.recording.chunk_check import CheckedReader

    return CheckedReader(stream, skip_offsets, decoder_factories=[DecoderFactory(), _JsonDecoderFactory()])


class _JsonDecoderFactory:
    def decoder_for(self, message_encoding: str, schema: Any):
        if message_encoding == "json":
            return lambda data: json.loads(data)
        return None


def read_profiles(reader) -> dict[str, CalibrationProfile]:
    """Calibration profiles attached to a recording, by name."""
    import yaml

    out: dict[str, CalibrationProfile] = {}
    for att in reader.iter_attachments():
        if att.name.startswith(PROFILE_PREFIX) and att.name.endswith(".yaml"):
            profile = profile_from_mapping(yaml.safe_load(io.BytesIO(att.data)), f"attachment {att.name}")
            out[profile.name] = profile
    return out


@dataclass
class RecordedFrame:
    """One raw frame read back, with its metadata (the JSON of ``/uwcam/image/metadata``)."""

    log_time_ns: int
    data: NDArray
    metadata: dict


def iter_recorded_frames(reader, start_time: int | None = None, end_time: int | None = None) -> Iterator[RecordedFrame]:
    """Raw frames in capture order with their metadata (matched by log time)."""
    pending_meta: dict[int, dict] = {}
    pending_img: dict[int, NDArray] = {}
    for _schema, channel, message, decoded in reader.iter_decoded_messages(
            topics=[IMAGE, IMAGE_METADATA], starting_at=start_time, ending_before=end_time):
        t = message.log_time
        if channel.topic == IMAGE:
            pending_img[t] = decode_raw_image(decoded)
        elif decoded.get("raw_kept", True):  # a frame decimated to fit the disk budget has no image
            pending_meta[t] = decoded
        if t in pending_img and t in pending_meta:
            yield RecordedFrame(t, pending_img.pop(t), pending_meta.pop(t))
