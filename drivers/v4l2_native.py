"""A V4L2 device driven natively through linuxpy's ioctls: formats, controls in their own units, capture.

OpenCV's V4L2 backend guesses: its ``CAP_PROP_EXPOSURE`` is ``V4L2_CID_EXPOSURE_ABSOLUTE`` in
**100 µs units**, it hides what a control's range is and whether the device clamped a value,
and it delivers 8-bit BGR only. Here every control is enumerated with its range, step, menu and
flags (``VIDIOC_QUERY_EXT_CTRL``/``QUERYMENU``), set and then read back (``S_CTRL``/``G_CTRL``),
so what the camera really does is what is reported and what frames are labelled with. Formats
are enumerated with their frame sizes (``ENUM_FMT``/``ENUM_FRAMESIZES``), 16-bit and Bayer
included, and frames come from memory-mapped buffers (``REQBUFS``, ``QBUF``/``DQBUF``) at the
format's own depth.

Every ioctl goes through linuxpy (``linuxpy.ioctl.ioctl`` → ``fcntl.ioctl``); opening, waiting
and mapping go through :data:`SYSTEM`, so the tests replace the kernel at exactly that boundary.
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import select
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from linuxpy.ioctl import ioctl
from linuxpy.video import raw
from linuxpy.video.device import IOC, BufferType, ControlFlag, ControlType, Memory

from uwcam.drivers.base import ConfigurationError, CorruptFrame, DeviceLost, FrameTimeout

# Control ids (linux/v4l2-controls.h).
CID_BRIGHTNESS = 0x00980900
CID_AUTO_WHITE_BALANCE = 0x0098090C
CID_GAMMA = 0x00980910
CID_GAIN = 0x00980913
CID_WHITE_BALANCE_TEMPERATURE = 0x0098091A
CID_BACKLIGHT_COMPENSATION = 0x0098091C
CID_EXPOSURE_AUTO = 0x009A0901
CID_EXPOSURE_ABSOLUTE = 0x009A0902
CID_EXPOSURE_AUTO_PRIORITY = 0x009A0903
EXPOSURE_MANUAL = 1  # enum v4l2_exposure_auto_type: V4L2_EXPOSURE_MANUAL

EXPOSURE_UNIT_US = 100.0
"""``V4L2_CID_EXPOSURE_ABSOLUTE`` counts 100 µs units: 1 is 1/10000 s, 10000 is 1 s (V4L2 spec)."""


def exposure_to_device(exposure_us: float) -> int:
    """Exposure time in µs → ``V4L2_CID_EXPOSURE_ABSOLUTE`` value (100 µs units), at least 1."""
    return max(1, int(round(exposure_us / EXPOSURE_UNIT_US)))


def exposure_from_device(value: int) -> float:
    """``V4L2_CID_EXPOSURE_ABSOLUTE`` value (100 µs units) → exposure time in µs."""
    return float(value) * EXPOSURE_UNIT_US


def fourcc_code(name: str) -> int:
    """'YUYV' → the little-endian 32-bit code V4L2 uses."""
    name = name.ljust(4)[:4]
    return sum(ord(c) << (8 * i) for i, c in enumerate(name))


def fourcc_name(code: int) -> str:
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)).rstrip("\0 ")


# V4L2 four-character codes → how a frame of them becomes (H, W, 3) RGB, and at what depth.
# Raw Bayer and RGB go through uwcam.drivers.pixels (GenICam names); YUV and JPEG through OpenCV.
# Bayer 10/12/16 arrive in 16-bit little-endian containers (V4L2 'BG10', 'BG12', 'BYR2', ...).
BAYER = {
    "BA81": ("BayerBG", 8), "GBRG": ("BayerGB", 8), "GRBG": ("BayerGR", 8), "RGGB": ("BayerRG", 8),
    "BG10": ("BayerBG", 10), "GB10": ("BayerGB", 10), "BA10": ("BayerGR", 10), "RG10": ("BayerRG", 10),
    "BG12": ("BayerBG", 12), "GB12": ("BayerGB", 12), "BA12": ("BayerGR", 12), "RG12": ("BayerRG", 12),
    "BYR2": ("BayerBG", 16), "GB16": ("BayerGB", 16), "GR16": ("BayerGR", 16), "RG16": ("BayerRG", 16),
}
RGB = {"RGB3": ("RGB8", 3), "BGR3": ("BGR8", 3)}
MONOCHROME = {"GREY", "Y10 ", "Y10", "Y12", "Y16", "Y16 ", "Y10P", "Y12P"}
DECODABLE = {"YUYV", "UYVY", "MJPG", "JPEG", *BAYER, *RGB}

PREFERENCE = ["BYR2", "GB16", "GR16", "RG16", "BG12", "GB12", "BA12", "RG12", "BG10", "GB10", "BA10", "RG10",
              "RGB3", "BGR3", "YUYV", "UYVY", "BA81", "GBRG", "GRBG", "RGGB", "MJPG", "JPEG"]
"""Which offered format to take when none is asked for: the deepest, least processed first
(raw 16-bit Bayer, then RGB, then YUV 4:2:2), lossy JPEG last; H.264 is never taken."""


def bit_depth(fourcc: str) -> int:
    """Bits per channel a frame of this format carries (8 for YUV, RGB24 and JPEG)."""
    return BAYER[fourcc][1] if fourcc in BAYER else 8


def decode(fourcc: str, data: bytes | memoryview | NDArray, width: int, height: int,
           bytes_per_line: int) -> NDArray:
    """(H, W, 3) RGB array (uint8, or uint16 for deep Bayer) from one buffer's bytes.

    ``bytes_per_line`` is the stride V4L2 reported; padding at the end of each line is dropped.
    """
    from uwcam.drivers.pixels import decode as decode_pixels, refuse_monochrome

    buf = np.frombuffer(data, dtype=np.uint8)
    if fourcc in MONOCHROME:
        refuse_monochrome("Mono" + str(bit_depth(fourcc)))
    if fourcc in ("MJPG", "JPEG"):
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape[:2] != (height, width):
            raise CorruptFrame(f"{fourcc} frame of {buf.size} bytes does not decode to {width}×{height}")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    bytes_per_pixel = {"YUYV": 2, "UYVY": 2}.get(fourcc) or (RGB[fourcc][1] if fourcc in RGB else None) \
        or (1 if fourcc in BAYER and BAYER[fourcc][1] == 8 else 2 if fourcc in BAYER else None)
    if bytes_per_pixel is None:
        raise ConfigurationError(f"V4L2 format {fourcc} cannot be decoded; choose one of {', '.join(sorted(DECODABLE))}")
    stride = bytes_per_line or width * bytes_per_pixel
    if buf.size < stride * (height - 1) + width * bytes_per_pixel:
        raise CorruptFrame(f"{fourcc} frame has {buf.size} bytes, needs {stride * height} for {width}×{height}")
    rows = np.lib.stride_tricks.as_strided(buf, shape=(height, width * bytes_per_pixel), strides=(stride, 1))
    if fourcc in ("YUYV", "UYVY"):
        code = cv2.COLOR_YUV2RGB_YUYV if fourcc == "YUYV" else cv2.COLOR_YUV2RGB_UYVY
        return cv2.cvtColor(np.ascontiguousarray(rows).reshape(height, width, 2), code)
    packed = np.ascontiguousarray(rows).reshape(-1)
    if fourcc in RGB:
        image, _ = decode_pixels(RGB[fourcc][0], packed, width, height)
        return np.ascontiguousarray(image)
    name, bits = BAYER[fourcc]
    values = packed if bits == 8 else packed.view("<u2")
    image, _ = decode_pixels(f"{name}{bits}", values, width, height)
    return image


@dataclass(frozen=True)
class Control:
    """One control as the device describes it (``VIDIOC_QUERY_EXT_CTRL``), in the device's units."""

    id: int
    name: str
    type: int
    minimum: int
    maximum: int
    step: int
    default: int
    flags: int
    menu: dict[int, str] = field(default_factory=dict)

    @property
    def read_only(self) -> bool:
        return bool(self.flags & (ControlFlag.READ_ONLY | ControlFlag.DISABLED))

    def offers(self) -> str:
        """What the control accepts, in words: a range with its step, or the menu's entries."""
        if self.menu:
            return ", ".join(f"{k} {v}" for k, v in sorted(self.menu.items()))
        if self.type == ControlType.BOOLEAN:
            return "0 or 1"
        return f"{self.minimum}…{self.maximum} in steps of {self.step}"


@dataclass(frozen=True)
class FormatOffer:
    """One pixel format the device offers and its frame sizes (discrete, or stepwise bounds)."""

    fourcc: str
    description: str
    compressed: bool
    sizes: tuple[tuple[int, int], ...]

    def __str__(self) -> str:
        sizes = ", ".join(f"{w}×{h}" for w, h in self.sizes[:8]) + (" …" if len(self.sizes) > 8 else "")
        return f"{self.fourcc} ({self.description}{'; compressed' if self.compressed else ''}: {sizes})"


class System:
    """The operating-system calls around the ioctls: open, close, wait for a frame, map a buffer."""

    @staticmethod
    def open(path: str) -> int:
        return os.open(path, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)

    @staticmethod
    def close(fd: int) -> None:
        os.close(fd)

    @staticmethod
    def wait_readable(fd: int, timeout_s: float) -> bool:
        readable, _, _ = select.select([fd], [], [], timeout_s)
        return bool(readable)

    @staticmethod
    def map(fd: int, length: int, offset: int) -> mmap.mmap:
        return mmap.mmap(fd, length, offset=offset)


SYSTEM = System()


class Refused(ConfigurationError):
    """The device refused a request; ``errno`` says how (EINVAL, ERANGE, EACCES...)."""

    def __init__(self, what: str, error: OSError) -> None:
        super().__init__(f"{what}: {os.strerror(error.errno or 0)}")
        self.errno = error.errno


CAPTURE = BufferType.VIDEO_CAPTURE


class NativeDevice:
    """One open V4L2 capture device. Not thread-safe (the supervisor's thread owns it)."""

    def __init__(self, path: str, system: System | None = None) -> None:
        self.system = system or SYSTEM
        self.path = path
        try:
            self.fd = self.system.open(path)
        except FileNotFoundError:
            raise DeviceLost(f"{path} does not exist (camera unplugged?)") from None
        except PermissionError:
            raise ConfigurationError(f"no permission to open {path}: add the user to the 'video' group") from None
        except OSError as exc:
            raise DeviceLost(f"cannot open {path}: {exc.strerror}") from None
        caps = raw.v4l2_capability()
        try:
            ioctl(self.fd, IOC.QUERYCAP, caps)
        except OSError as exc:
            self.system.close(self.fd)
            raise ConfigurationError(f"{path} is not a V4L2 device ({exc.strerror})") from None
        self.card = caps.card.decode(errors="replace")
        self.driver = caps.driver.decode(errors="replace")
        self.bus_info = caps.bus_info.decode(errors="replace")
        device_caps = caps.device_caps or caps.capabilities
        if not device_caps & 0x1:  # V4L2_CAP_VIDEO_CAPTURE
            self.system.close(self.fd)
            raise ConfigurationError(f"{path} ({self.card}) cannot capture video; it is another node of the camera "
                                     "(metadata or H.264): choose the /dev/video node that lists YUYV or MJPG")
        self._maps: list[mmap.mmap] = []
        self._streaming = False
        self._controls: dict[int, Control] | None = None

    # -- enumeration -----------------------------------------------------------------------

    def formats(self) -> list[FormatOffer]:
        """Every capture format with its frame sizes."""
        offers = []
        for desc in self._enumerate(IOC.ENUM_FMT, raw.v4l2_fmtdesc, 64, type=CAPTURE):
            offers.append(FormatOffer(fourcc_name(desc.pixelformat), desc.description.decode(errors="replace"),
                                      bool(desc.flags & 0x1), tuple(self._sizes(desc.pixelformat))))
        return offers

    def _sizes(self, code: int) -> list[tuple[int, int]]:
        sizes = []
        for size in self._enumerate(IOC.ENUM_FRAMESIZES, raw.v4l2_frmsizeenum, 256, pixel_format=code):
            if size.type == 1:  # V4L2_FRMSIZE_TYPE_DISCRETE
                sizes.append((size.discrete.width, size.discrete.height))
            else:  # stepwise or continuous: the bounds
                s = size.stepwise
                sizes += [(s.min_width, s.min_height), (s.max_width, s.max_height)]
                break
        return sizes

    def controls(self) -> dict[int, Control]:
        """Every control the device has (cached: a device's controls do not change while open)."""
        if self._controls is not None:
            return self._controls
        found: dict[int, Control] = {}
        query = raw.v4l2_query_ext_ctrl()
        query.id = ControlFlag.NEXT_CTRL | ControlFlag.NEXT_COMPOUND
        for _ in range(1024):
            if not self._query(IOC.QUERY_EXT_CTRL, query):
                break
            if query.type != ControlType.CTRL_CLASS:
                menu = self._menu(query) if query.type in (ControlType.MENU, ControlType.INTEGER_MENU) else {}
                found[query.id] = Control(query.id, query.name.decode(errors="replace"), query.type, query.minimum,
                                          query.maximum, query.step, query.default_value, query.flags, menu)
            query.id |= ControlFlag.NEXT_CTRL | ControlFlag.NEXT_COMPOUND
        self._controls = found
        return found

    def _menu(self, query: raw.v4l2_query_ext_ctrl) -> dict[int, str]:
        entries = {}
        for index in range(query.minimum, query.maximum + 1):
            item = raw.v4l2_querymenu()
            item.id, item.index = query.id, index
            try:
                ioctl(self.fd, IOC.QUERYMENU, item)
            except OSError as exc:
                if exc.errno == errno.EINVAL:  # a hole in the menu: this entry is not offered
                    continue
                raise self._lost_or(exc, "QUERYMENU") from None
            entries[index] = item.name.decode(errors="replace") if query.type == ControlType.MENU else str(item.value)
        return entries

    def _enumerate(self, request: int, kind: type, limit: int, **fields: int) -> Iterator:
        """The items of one of the device's lists: a ``kind`` struct with ``fields`` and index 0, 1, …
        filled in by ``request`` until the device says the list has ended, at most ``limit`` of them."""
        for index in range(limit):
            struct = kind(index=index, **fields)
            if not self._query(request, struct):
                return
            yield struct

    def _query(self, request: int, struct: object) -> bool:
        """One enumeration step; False at the end of the list (EINVAL)."""
        try:
            ioctl(self.fd, request, struct)
            return True
        except OSError as exc:
            if exc.errno in (errno.EINVAL, errno.ENOTTY):
                return False
            raise self._lost_or(exc, getattr(request, "name", str(request))) from None

    def _lost_or(self, exc: OSError, what: str) -> Exception:
        if exc.errno in (errno.ENODEV, errno.EIO, errno.ENXIO):
            return DeviceLost(f"{self.path} ({self.card}) went away during {what}: {exc.strerror}")
        if exc.errno == errno.EBUSY:
            return DeviceLost(f"{self.path} is busy ({what}): another program (mavlink-camera-manager on BlueOS?) is "
                              "streaming from it; use the 'stream' camera driver on its RTSP stream instead")
        return Refused(what, exc)

    # -- controls ----------------------------------------------------------------------------

    def get(self, cid: int) -> int:
        control = raw.v4l2_control(cid)
        try:
            ioctl(self.fd, IOC.G_CTRL, control)
        except OSError as exc:
            raise self._lost_or(exc, f"reading control {cid:#010x}") from None
        return int(control.value)

    def set(self, cid: int, value: int) -> int:
        """Set a control and return what the device reports back (it may clamp or round)."""
        control = raw.v4l2_control(cid, int(value))
        try:
            ioctl(self.fd, IOC.S_CTRL, control)
        except OSError as exc:
            raise self._lost_or(exc, f"setting control {cid:#010x} to {value}") from None
        return self.get(cid)

    # -- format, rate, streaming -----------------------------------------------------------

    def set_format(self, fourcc: str, width: int | None, height: int | None) -> tuple[str, int, int, int, int]:
        """Ask for a format and size; (fourcc, width, height, bytes per line, bytes per image) it chose."""
        current = self.get_format()
        fmt = raw.v4l2_format()
        fmt.type = CAPTURE
        fmt.fmt.pix.pixelformat = fourcc_code(fourcc)
        fmt.fmt.pix.width = width or current[1]
        fmt.fmt.pix.height = height or current[2]
        fmt.fmt.pix.field = 1  # V4L2_FIELD_NONE: progressive frames
        try:
            ioctl(self.fd, IOC.S_FMT, fmt)
        except OSError as exc:
            raise self._lost_or(exc, f"setting format {fourcc}") from None
        return self.get_format()

    def get_format(self) -> tuple[str, int, int, int, int]:
        fmt = raw.v4l2_format()
        fmt.type = CAPTURE
        try:
            ioctl(self.fd, IOC.G_FMT, fmt)
        except OSError as exc:
            raise self._lost_or(exc, "reading the format") from None
        pix = fmt.fmt.pix
        return fourcc_name(pix.pixelformat), pix.width, pix.height, pix.bytesperline, pix.sizeimage

    def set_frame_rate(self, fps: float) -> float | None:
        """Ask for a frame rate; the rate the device chose (None where it has no frame-interval control)."""
        from fractions import Fraction

        parm = raw.v4l2_streamparm()
        parm.type = CAPTURE
        interval = Fraction(1.0 / fps).limit_denominator(100000)
        parm.parm.capture.timeperframe.numerator = interval.numerator
        parm.parm.capture.timeperframe.denominator = interval.denominator
        try:
            ioctl(self.fd, IOC.S_PARM, parm)
        except OSError as exc:
            if exc.errno in (errno.EINVAL, errno.ENOTTY):
                return None
            raise self._lost_or(exc, "setting the frame rate") from None
        tpf = parm.parm.capture.timeperframe
        return tpf.denominator / tpf.numerator if tpf.numerator else None

    def start(self, buffers: int = 4) -> None:
        """Map ``buffers`` kernel buffers, queue them and start streaming."""
        request = raw.v4l2_requestbuffers()
        request.count, request.type, request.memory = buffers, CAPTURE, Memory.MMAP
        try:
            ioctl(self.fd, IOC.REQBUFS, request)
            if request.count < 1:
                raise ConfigurationError(f"{self.path} gave no capture buffers")
            for index in range(request.count):
                buf = self._buffer(index)
                ioctl(self.fd, IOC.QUERYBUF, buf)
                self._maps.append(self.system.map(self.fd, buf.length, buf.m.offset))
                ioctl(self.fd, IOC.QBUF, buf)
            ioctl(self.fd, IOC.STREAMON, ctypes.c_int(CAPTURE))
        except OSError as exc:
            raise self._lost_or(exc, "starting the stream") from None
        self._streaming = True

    @staticmethod
    def _buffer(index: int = 0) -> raw.v4l2_buffer:
        buf = raw.v4l2_buffer()
        buf.index, buf.type, buf.memory = index, CAPTURE, Memory.MMAP
        return buf

    def read(self, timeout_s: float) -> tuple[bytes, int, int]:
        """(the frame's bytes, the driver's sequence number, its timestamp in ns) of the next frame."""
        if not self.system.wait_readable(self.fd, timeout_s):
            raise FrameTimeout(f"no frame from {self.path} within {timeout_s:g} s")
        buf = self._buffer()
        try:
            ioctl(self.fd, IOC.DQBUF, buf)
        except OSError as exc:
            if exc.errno == errno.EAGAIN:
                raise FrameTimeout(f"no frame from {self.path} within {timeout_s:g} s") from None
            raise self._lost_or(exc, "dequeuing a frame") from None
        try:
            if buf.flags & 0x40:  # V4L2_BUF_FLAG_ERROR: the driver says the data is damaged
                raise CorruptFrame(f"{self.path} marked frame {buf.sequence} as damaged")
            data = bytes(self._maps[buf.index][: buf.bytesused])  # the copy: the buffer goes back to the driver
        finally:
            try:
                ioctl(self.fd, IOC.QBUF, buf)
            except OSError as exc:
                raise self._lost_or(exc, "re-queuing a buffer") from None
        stamp_ns = buf.timestamp.secs * 1_000_000_000 + buf.timestamp.usecs * 1000
        return data, int(buf.sequence), int(stamp_ns)

    def stop(self) -> None:
        if self._streaming:
            self._streaming = False
            try:
                ioctl(self.fd, IOC.STREAMOFF, ctypes.c_int(CAPTURE))
                for m in self._maps:
                    m.close()
                self._maps.clear()
                request = raw.v4l2_requestbuffers()
                request.count, request.type, request.memory = 0, CAPTURE, Memory.MMAP
                ioctl(self.fd, IOC.REQBUFS, request)
            except OSError:
                pass  # stopping a device that went away: nothing left to release
        self._maps.clear()

    def close(self) -> None:
        self.stop()
        if self.fd >= 0:
            try:
                self.system.close(self.fd)
            finally:
                self.fd = -1
