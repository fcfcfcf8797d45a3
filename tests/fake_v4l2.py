"""A fake V4L2 kernel at the ioctl boundary, answering from a real camera's recorded table.

The native V4L2 driver issues every ioctl through linuxpy (``linuxpy.ioctl`` → ``fcntl.ioctl``)
and opens, waits and maps through ``uwcam.drivers.v4l2_native.SYSTEM``; :func:`install` replaces
exactly those two, so everything above them (linuxpy's structures and request codes, the
driver's logic) runs as it would on a device. The answers follow uvcvideo's rules: integer
controls clamped to their range and rounded to their step, menu values outside the menu
refused (EINVAL), a control left inactive by its automatic mode refused (EACCES), the nearest
frame size taken for S_FMT, EINVAL at the end of every enumeration.

Frames are rendered from a scene whose brightness is proportional to the exposure time the
control holds, so a wrongly scaled exposure shows in the pixels as well as in the control.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import select
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from linuxpy.video.device import IOC, ControlFlag, ControlType

DATA = Path(__file__).parent / "data"
TYPES = {"int": ControlType.INTEGER, "bool": ControlType.BOOLEAN, "menu": ControlType.MENU,
         "intmenu": ControlType.INTEGER_MENU}
CLASSES = {0x00980001: "User Controls", 0x009A0001: "Camera Controls"}
INACTIVE_UNLESS = {0x009A0902: (0x009A0901, {1}), 0x0098091A: (0x0098090C, {0})}
"""control → (its automatic-mode control, values of that control under which it is active)."""


@dataclass
class FakeControl:
    """One control as the kernel's struct v4l2_queryctrl describes it, its menu and its value."""

    id: int
    name: str
    type: int
    minimum: int = 0
    maximum: int = 1
    step: int = 1
    default: int = 0
    menu: dict[int, str] = field(default_factory=dict)
    value: int = 0
    flags: int = 0


@dataclass
class FakeFormat:
    fourcc: str
    description: str
    compressed: bool
    sizes: list[tuple[int, int]]


def parse_table(path: Path) -> tuple[dict[int, FakeControl], list[FakeFormat]]:
    """Controls (``v4l2-ctl --list-ctrls`` lines, menu entries below) and formats of a table file."""
    controls: dict[int, FakeControl] = {}
    formats: list[FakeFormat] = []
    section, last = "", None
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        if line.startswith("["):
            section = line.strip("[] ")
            continue
        if section == "controls":
            m = re.match(r"\s*(\w+) 0x([0-9a-f]{8}) \((\w+)\)\s*:(.*)$", line)
            if m:
                values = dict(re.findall(r"(\w+)=([-\w,]+)", m.group(4)))
                flags = ControlFlag.INACTIVE if "inactive" in values.get("flags", "") else 0
                if "read-only" in values.get("flags", ""):
                    flags |= ControlFlag.READ_ONLY
                kind = TYPES[m.group(3)]
                last = FakeControl(int(m.group(2), 16), m.group(1), kind, int(values.get("min", 0)),
                                   int(values.get("max", 1)), int(values.get("step", 1)), int(values["default"]),
                                   value=int(values["value"]), flags=flags)
                controls[last.id] = last
            elif (m := re.match(r"\s+(\d+): (.+)$", line)) and last is not None:
                last.menu[int(m.group(1))] = m.group(2).strip()
        elif section == "formats":
            head, sizes = line.rsplit(":", 1)
            fourcc, flag, description = head.split(" ", 2)
            formats.append(FakeFormat(fourcc, description, flag == "compressed",
                                      [tuple(int(v) for v in s.split("x")) for s in sizes.split()]))
    return controls, formats


BYTES_PER_PIXEL = {"YUYV": 2, "UYVY": 2, "RGB3": 3, "BGR3": 3, "BA81": 1, "RGGB": 1, "GREY": 1,
                   "BYR2": 2, "RG16": 2, "Y16 ": 2, "Y16": 2}


def code(fourcc: str) -> int:
    return sum(ord(c) << (8 * i) for i, c in enumerate(fourcc.ljust(4)[:4]))


def name(value: int) -> str:
    return "".join(chr((value >> (8 * i)) & 0xFF) for i in range(4)).rstrip("\0 ")


class FakeMap:
    """What mmap gives: a writable buffer the kernel fills and the driver reads."""

    def __init__(self, length: int) -> None:
        self.data = bytearray(length)

    def __getitem__(self, item):
        return self.data[item]

    def close(self) -> None:
        pass


def scene_rgb(width: int, height: int) -> np.ndarray:
    """Linear radiance of a test scene per second of exposure (counts/s at unity gain), RGB."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    base = np.stack([2e6 + 0 * x, 4e6 + 0 * x, 6e6 + 0 * y], axis=-1)
    base[: height // 2, : width // 2] *= [1.5, 0.5, 0.25]  # a coloured quadrant: channel order shows
    return base


class FakeUVC:
    """One fake capture node: controls, formats, buffers, frames."""

    def __init__(self, table: Path, path: str, card: str = "H264 USB Camera: USB Camera",
                 gain_per_step: float = 0.0) -> None:
        self.controls, self.formats = parse_table(table)
        self.path, self.card = path, card
        self.log: list[tuple[str, int, int]] = []  # ("S_CTRL", id, value) as the driver sent them
        first = self.formats[0]
        self.format = (first.fourcc, *first.sizes[0])
        self.interval = (1, 30)
        self.buffers: list[FakeMap] = []
        self.queued: list[int] = []
        self.filled: list[int] = []
        self.streaming = False
        self.sequence = 0
        self.read_fd = self.write_fd = -1
        self.gain_per_step = gain_per_step
        self.busy = False

    # -- system calls -------------------------------------------------------------------
    def open(self, path: str) -> int:
        if path != self.path:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", path)
        self.read_fd, self.write_fd = os.pipe()
        os.set_blocking(self.read_fd, False)
        return self.read_fd

    def close(self, fd: int) -> None:
        os.close(self.read_fd)
        os.close(self.write_fd)
        self.read_fd = self.write_fd = -1

    def wait_readable(self, fd: int, timeout_s: float) -> bool:
        return bool(select.select([fd], [], [], timeout_s)[0])

    def map(self, fd: int, length: int, offset: int) -> FakeMap:
        return self.buffers[offset // 4096]

    # -- the ioctl boundary -------------------------------------------------------------
    def ioctl(self, fd, request, arg=None, *rest):
        if fd != self.read_fd:
            raise OSError(errno.EBADF, "bad file descriptor")
        for name_ in ("QUERYCAP", "ENUM_FMT", "ENUM_FRAMESIZES", "QUERY_EXT_CTRL", "QUERYMENU", "G_CTRL", "S_CTRL",
                      "G_FMT", "S_FMT", "S_PARM", "G_PARM", "REQBUFS", "QUERYBUF", "QBUF", "DQBUF", "STREAMON",
                      "STREAMOFF"):
            if request == getattr(IOC, name_):
                getattr(self, "_" + name_.lower())(arg)
                return 0
        raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")

    def _querycap(self, caps) -> None:
        caps.driver, caps.card, caps.bus_info = b"uvcvideo", self.card.encode(), b"usb-fake-1.4"
        caps.capabilities, caps.device_caps = 0x84A00001, 0x04200001

    def _enum_fmt(self, desc) -> None:
        if desc.index >= len(self.formats):
            raise OSError(errno.EINVAL, "end")
        f = self.formats[desc.index]
        desc.pixelformat, desc.description, desc.flags = code(f.fourcc), f.description.encode(), int(f.compressed)

    def _enum_framesizes(self, size) -> None:
        f = next((f for f in self.formats if code(f.fourcc) == size.pixel_format), None)
        if f is None or size.index >= len(f.sizes):
            raise OSError(errno.EINVAL, "end")
        size.type = 1
        size.discrete.width, size.discrete.height = f.sizes[size.index]

    def _all_ids(self) -> list[int]:
        return sorted([*self.controls, *CLASSES])

    def _query_ext_ctrl(self, q) -> None:
        wanted = q.id & ~(ControlFlag.NEXT_CTRL | ControlFlag.NEXT_COMPOUND)
        if q.id & ControlFlag.NEXT_CTRL:
            later = [i for i in self._all_ids() if i > wanted]
            if not later:
                raise OSError(errno.EINVAL, "end")
            wanted = later[0]
        if wanted in CLASSES:
            q.id, q.type, q.name, q.flags = wanted, ControlType.CTRL_CLASS, CLASSES[wanted].encode(), 0x44
            return
        c = self.controls.get(wanted)
        if c is None:
            raise OSError(errno.EINVAL, "no such control")
        q.id, q.type, q.name = c.id, c.type, c.name.encode()[:31]
        q.minimum, q.maximum, q.step, q.default_value, q.flags = c.minimum, c.maximum, c.step, c.default, self._flags(c)

    def _flags(self, c: FakeControl) -> int:
        flags = c.flags & ~ControlFlag.INACTIVE
        if c.id in INACTIVE_UNLESS:
            auto, active = INACTIVE_UNLESS[c.id]
            if self.controls[auto].value not in active:
                flags |= ControlFlag.INACTIVE
        return flags

    def _querymenu(self, item) -> None:
        c = self.controls.get(item.id)
        if c is None or item.index not in c.menu:
            raise OSError(errno.EINVAL, "no such entry")
        item.name = c.menu[item.index].encode()

    def _g_ctrl(self, control) -> None:
        c = self.controls.get(control.id)
        if c is None:
            raise OSError(errno.EINVAL, "no such control")
        control.value = c.value

    def _s_ctrl(self, control) -> None:
        self.log.append(("S_CTRL", control.id, control.value))
        c = self.controls.get(control.id)
        if c is None:
            raise OSError(errno.EINVAL, "no such control")
        if c.flags & ControlFlag.READ_ONLY:
            raise OSError(errno.EACCES, "read-only")
        if self._flags(c) & ControlFlag.INACTIVE:
            raise OSError(errno.EACCES, "inactive while its automatic mode is on")
        value = control.value
        if c.type == ControlType.MENU:
            if value not in c.menu:
                raise OSError(errno.EINVAL, "not in the menu")
        elif c.type == ControlType.BOOLEAN:
            value = int(bool(value))
        else:  # uvcvideo: clamp to the range, then round to the step
            value = min(max(value, c.minimum), c.maximum)
            value = c.minimum + (value - c.minimum + c.step // 2) // c.step * c.step
        c.value = value

    def _fill_format(self, pix) -> None:
        fourcc, w, h = self.format
        bpp = BYTES_PER_PIXEL.get(fourcc, 0)
        pix.pixelformat, pix.width, pix.height, pix.field = code(fourcc), w, h, 1
        pix.bytesperline = w * bpp
        pix.sizeimage = w * h * bpp if bpp else w * h * 2  # JPEG: the driver's upper bound

    def _g_fmt(self, fmt) -> None:
        self._fill_format(fmt.fmt.pix)

    def _s_fmt(self, fmt) -> None:
        if self.streaming or self.buffers:
            raise OSError(errno.EBUSY, "busy")
        pix = fmt.fmt.pix
        f = next((f for f in self.formats if code(f.fourcc) == pix.pixelformat), self.formats[0])
        w, h = min(f.sizes, key=lambda s: abs(s[0] - pix.width) + abs(s[1] - pix.height))
        self.format = (f.fourcc, w, h)
        self._fill_format(pix)

    def _g_parm(self, parm) -> None:
        parm.parm.capture.capability = 0x1000
        parm.parm.capture.timeperframe.numerator, parm.parm.capture.timeperframe.denominator = self.interval

    def _s_parm(self, parm) -> None:
        tpf = parm.parm.capture.timeperframe
        asked = tpf.denominator / tpf.numerator
        self.interval = (1, min((30, 25, 15), key=lambda f: abs(f - asked)))
        self._g_parm(parm)

    def _reqbufs(self, req) -> None:
        if self.busy:
            raise OSError(errno.EBUSY, "Device or resource busy")
        if req.count == 0:
            self.buffers, self.queued, self.filled = [], [], []
            return
        self.buffers = [FakeMap(self._size()) for _ in range(min(req.count, 4))]
        req.count = len(self.buffers)

    def _size(self) -> int:
        class Pix(ctypes.Structure):
            _fields_ = [(n, ctypes.c_uint) for n in ("pixelformat", "width", "height", "field", "bytesperline",
                                                      "sizeimage")]
        pix = Pix()
        self._fill_format(pix)
        return pix.sizeimage

    def _querybuf(self, buf) -> None:
        buf.length, buf.m.offset = len(self.buffers[buf.index].data), buf.index * 4096

    def _qbuf(self, buf) -> None:
        self.queued.append(buf.index)
        self._produce()

    def _dqbuf(self, buf) -> None:
        if not self.filled:
            raise OSError(errno.EAGAIN, "no buffer ready")
        index, used = self.filled.pop(0)
        os.read(self.read_fd, 1)
        buf.index, buf.bytesused, buf.sequence, buf.flags = index, used, self.sequence, 0
        buf.timestamp.secs, buf.timestamp.usecs = 1000 + self.sequence, 0
        self.sequence += 1

    def _streamon(self, arg) -> None:
        self.streaming = True
        self._produce()

    def _streamoff(self, arg) -> None:
        self.streaming = False
        self.queued, self.filled = [], []

    # -- frames ---------------------------------------------------------------------------
    def exposure_s(self) -> float:
        return self.controls[0x009A0902].value * 100e-6

    def _produce(self) -> None:
        while self.streaming and self.queued:
            index = self.queued.pop(0)
            payload = self.render()
            self.buffers[index].data[: len(payload)] = payload
            self.filled.append((index, len(payload)))
            os.write(self.write_fd, b"x")

    def linear_counts(self) -> np.ndarray:
        """The scene's signal at the current exposure and gain, before the camera's encoding."""
        fourcc, w, h = self.format
        gain = 10 ** (self.controls[0x00980913].value * self.gain_per_step / 20)
        return scene_rgb(w, h) * self.exposure_s() * gain

    def render(self) -> bytes:
        fourcc, w, h = self.format
        counts = self.linear_counts()
        if fourcc in ("BYR2", "RG16"):
            rgb = np.clip(counts, 0, 65535).astype(np.uint16)
            mosaic = np.empty((h, w), np.uint16)  # BGGR (BYR2) or RGGB (RG16) 2×2 pattern
            first, last = (2, 0) if fourcc == "BYR2" else (0, 2)
            mosaic[0::2, 0::2] = rgb[0::2, 0::2, first]
            mosaic[0::2, 1::2] = rgb[0::2, 1::2, 1]
            mosaic[1::2, 0::2] = rgb[1::2, 0::2, 1]
            mosaic[1::2, 1::2] = rgb[1::2, 1::2, last]
            return mosaic.astype("<u2").tobytes()
        rgb8 = np.clip(counts / 256.0, 0, 255).astype(np.uint8)
        if fourcc == "YUYV":  # BT.601, limited range (Y 16–235), as UVC cameras send it
            r, g, b = (rgb8[..., k] / 255.0 for k in range(3))
            y = 16 + 65.481 * r + 128.553 * g + 24.966 * b
            cb = 128 - 37.797 * r - 74.203 * g + 112.0 * b
            cr = 128 + 112.0 * r - 93.786 * g - 18.214 * b
            packed = np.empty((h, w, 2), np.uint8)
            packed[..., 0] = np.round(y)
            packed[:, 0::2, 1] = np.round((cb[:, 0::2] + cb[:, 1::2]) / 2)
            packed[:, 1::2, 1] = np.round((cr[:, 0::2] + cr[:, 1::2]) / 2)
            return packed.tobytes()
        if fourcc == "MJPG":
            ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            return jpeg.tobytes()
        if fourcc == "RGB3":
            return rgb8.tobytes()
        if fourcc in ("GREY",):
            return rgb8[..., 1].tobytes()
        raise AssertionError(f"the fake cannot render {fourcc}")


def install(monkeypatch, fake: FakeUVC) -> FakeUVC:
    """Put ``fake`` at the kernel boundary: linuxpy's fcntl.ioctl and the driver's system calls."""
    import linuxpy.ioctl

    from uwcam.drivers import v4l2_native

    class Fcntl:
        ioctl = staticmethod(fake.ioctl)

    monkeypatch.setattr(linuxpy.ioctl, "fcntl", Fcntl)
    monkeypatch.setattr(v4l2_native, "SYSTEM", fake)
    Path(fake.path).touch()  # the device node exists (the driver checks before opening)
    return fake
