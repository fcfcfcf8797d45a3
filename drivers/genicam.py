"""GenICam GenTL cameras through harvesters.

The GenTL producer (.cti) comes from the configuration or from GENICAM_GENTL64_PATH (a
path list of folders holding .cti files). Settings go through the camera's node map;
automatic exposure, gain and white balance, gamma and LUTs are switched off where the
camera has them, and what it lacks is reported. Multi-part payloads with one component
per sensor (3-chip cameras) are assembled into one registered frame.
"""

from __future__ import annotations

import contextlib
import glob
import os
import threading
import time

import numpy as np

from typing import Annotated

from pydantic import Field

from uwcam.drivers.options import ChannelNames, DriverOptions, Whole
from uwcam.drivers.base import (CameraDriver, CameraSettings, ConfigurationError, ConfigureReport, DeviceInfo,
                                DeviceLost, Frame, FrameTimeout)
from uwcam.drivers.pixels import assemble_components, decode, refuse_monochrome

# Node → value that keeps radiometry linear and fixed.
RADIOMETRY_OFF = {
    "ExposureAuto": "Off",
    "GainAuto": "Off",
    "BalanceWhiteAuto": "Off",
    "BlackLevelAuto": "Off",
    "GammaEnable": False,
    "LUTEnable": False,
}


def find_producers(cti: str | None = None) -> list[str]:
    """The .cti files to load: the configured one, or those on GENICAM_GENTL64_PATH."""
    if cti:
        if not os.path.isfile(cti):
            raise ConfigurationError(f"GenTL producer {cti} does not exist; give the path of your camera vendor's .cti file")
        return [cti]
    paths = [p for p in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep) if p]
    found = sorted(f for p in paths for f in glob.glob(os.path.join(p, "*.cti")))
    if not found:
        raise ConfigurationError(
            "no GenTL producer: set 'cti' in the camera configuration or GENICAM_GENTL64_PATH to the folder of "
            "your camera vendor's .cti file"
        )
    return found


# A GenTL producer serves its devices to one harvester per process: cameras on the same
# producers share it, counted, and it is reset when the last one closes.
_harvesters: dict[tuple[str, ...], list] = {}
_harvesters_lock = threading.Lock()


def _acquire_harvester(producers: list[str]):
    from harvesters.core import Harvester

    key = tuple(producers)
    with _harvesters_lock:
        if key not in _harvesters:
            h = Harvester()
            for cti in producers:
                h.add_file(cti)
            _harvesters[key] = [h, 0]
        _harvesters[key][1] += 1
        return _harvesters[key][0]


def _release_harvester(producers: list[str]) -> None:
    key = tuple(producers)
    with _harvesters_lock:
        entry = _harvesters.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] <= 0:
            del _harvesters[key]
            try:
                entry[0].reset()
            except Exception:
                pass


def component_array(component) -> np.ndarray:
    """A payload component's pixels: harvesters' decoded array, or for packed formats (which it
    leaves undecoded or empty) the raw bytes from the component's offset, for pixels.decode.
    Verified on the simulator's unpacked formats; the packed path by reading harvesters' code."""
    data = component.data
    if component.data_format.endswith("p") or data is None or data.size == 0:
        return np.frombuffer(component._buffer.raw_buffer, np.uint8, offset=component.data_offset)
    return data


# Entries of SFNC's ExposureTimeSelector / GainSelector that name one sensor of a multi-sensor
# (3-chip) camera, by channel name; the channel's own name is tried too.
CHANNEL_SELECTOR_VALUES = {"R": ("Red",), "G": ("Green",), "B": ("Blue",)}


def channel_selectors(node_map, selector: str, channel_names: tuple[str, ...]) -> list[str] | None:
    """The entry of ``selector`` for each channel, or None when the camera has no such selector
    or it does not name every channel (then one value serves all channels)."""
    if not hasattr(node_map, selector):
        return None
    try:
        options = list(getattr(node_map, selector).symbolics)
    except Exception:
        return None
    picked = []
    for name in channel_names:
        match = next((v for v in (*CHANNEL_SELECTOR_VALUES.get(name, ()), name) if v in options), None)
        if match is None:
            return None
        picked.append(match)
    return picked


class GenTLCamera(CameraDriver):
    class Options(DriverOptions):
        cti: str | None = None
        """Path of the vendor's GenTL producer (.cti); None: those on GENICAM_GENTL64_PATH."""
        serial_number: str | None = None
        channel_names: ChannelNames = ["R", "G", "B"]
        buffers: Annotated[Whole, Field(ge=1, le=64)] = 4

    """A GenICam camera (GigE Vision, USB3 Vision, CoaXPress…) via its vendor's GenTL producer."""

    name = "genicam"

    def __init__(self, cti: str | None = None, serial_number: str | None = None, channel_names: tuple[str, ...] = ("R", "G", "B"),
                 buffers: int = 4) -> None:
        self.producers = find_producers(cti)
        self.serial_number = serial_number
        self.channel_names = tuple(channel_names)
        self.buffers = buffers
        self._harvester = None
        self._acquirer = None
        self._exposure_us: float | None = None
        self._gain_db: float | None = None
        self._channel_exposure: tuple[float, ...] | None = None
        self._channel_gain: tuple[float, ...] | None = None
        self._selectors: dict[str, list[str] | None] = {}
        self.exposure_control = ""

    @classmethod
    def list_devices(cls, cti: str | None = None, **_) -> list[DeviceInfo]:
        producers = find_producers(cti)
        h = _acquire_harvester(producers)
        try:
            h.update()
            return [DeviceInfo(d.id_, str(d.serial_number), d.model, d.vendor) for d in h.device_info_list]
        finally:
            _release_harvester(producers)

    def open(self) -> DeviceInfo:
        self.close()
        self._harvester = _acquire_harvester(self.producers)

        def matching():
            return [d for d in self._harvester.device_info_list
                    if self.serial_number is None or str(d.serial_number) == str(self.serial_number)]

        for attempt in range(2):
            chosen = matching()
            if not chosen or attempt == 1:
                # Re-enumerate only when needed: update() invalidates acquirers already created
                # from this harvester (other sensors of a multi-sensor camera).
                self._harvester.update()
                chosen = matching()
            if not chosen:
                seen = ", ".join(str(d.serial_number) for d in self._harvester.device_info_list) or "none"
                raise DeviceLost(f"no GenTL camera with serial number {self.serial_number} (present: {seen})")
            info = chosen[0]
            try:
                self._acquirer = self._harvester.create({"serial_number": info.serial_number})
                self._acquirer.num_buffers = self.buffers
                break
            except Exception as exc:  # a stale entry for a device that came back: enumerate again
                if attempt == 1:
                    raise DeviceLost(f"cannot open GenTL camera {info.serial_number}: {exc}") from None
        return DeviceInfo(info.id_, str(info.serial_number), info.model, info.vendor)

    def _nodes(self):
        return self._acquirer.remote_device.node_map

    def configure(self, settings: CameraSettings) -> ConfigureReport:
        nm = self._nodes()
        report = ConfigureReport()
        for node, value in RADIOMETRY_OFF.items():
            if not hasattr(nm, node):
                continue  # the camera has no such automatic feature
            try:
                getattr(nm, node).value = value
            except Exception:
                report.radiometry_not_disabled.append(node)
        if hasattr(nm, "Gamma"):
            try:
                nm.Gamma.value = 1.0
            except Exception:
                report.radiometry_not_disabled.append("Gamma")
        wanted = {
            "PixelFormat": settings.pixel_format,
            "ExposureTime": settings.exposure_us,
            "Gain": settings.gain_db,
            "BlackLevel": settings.black_level,
            "AcquisitionFrameRate": settings.frame_rate,
        }
        if settings.region is not None:
            x, y, w, h = settings.region
            wanted.update({"Width": w, "Height": h, "OffsetX": x, "OffsetY": y})
        for node, value in wanted.items():
            if value is None:
                continue
            if not hasattr(nm, node):
                report.unsupported.append(node)
                continue
            if node == "PixelFormat" and value not in nm.PixelFormat.symbolics:
                raise ConfigurationError(
                    f"camera does not offer pixel format {value}; it offers {', '.join(nm.PixelFormat.symbolics)}"
                )
            try:
                getattr(nm, node).value = value
                report.applied[node] = getattr(nm, node).value
            except Exception as exc:
                report.unsupported.append(f"{node} ({exc})")
        refuse_monochrome(nm.PixelFormat.value)  # fail at start, clearly, not on the first frame
        # Per-channel exposure and gain where the camera selects its sensors (SFNC ExposureTimeSelector,
        # GainSelector: 3-chip cameras); one value for all otherwise; none where there is no such node.
        self._selectors = {node: channel_selectors(nm, selector, self.channel_names) if hasattr(nm, node) else None
                           for node, selector in (("ExposureTime", "ExposureTimeSelector"), ("Gain", "GainSelector"))}
        self.exposure_control = ("per-channel" if self._selectors["ExposureTime"] else
                                 "common" if hasattr(nm, "ExposureTime") else "")
        if settings.channel_exposure_us is not None or settings.channel_gain_db is not None:
            exposure = settings.channel_exposure_us or self._read_per_channel("ExposureTime")
            if exposure is not None:
                try:
                    self.set_exposure(tuple(exposure), settings.channel_gain_db)
                    report.applied["channel_exposure_us"] = list(self._channel_exposure or ())
                except ConfigurationError as exc:
                    report.unsupported.append(f"channel_exposure_us ({exc})")
        self._read_back()
        return report

    def _read_per_channel(self, node: str) -> tuple[float, ...] | None:
        """``node``'s value for each channel (through its selector), or its one value repeated; None if absent."""
        nm = self._nodes()
        if not hasattr(nm, node):
            return None
        selectors = self._selectors.get(node)
        if not selectors:
            return (float(getattr(nm, node).value),) * len(self.channel_names)
        selector = getattr(nm, "ExposureTimeSelector" if node == "ExposureTime" else "GainSelector")
        values = []
        for entry in selectors:
            selector.value = entry
            values.append(float(getattr(nm, node).value))
        return tuple(values)

    def _read_back(self) -> None:
        nm = self._nodes()
        self._exposure_us = float(nm.ExposureTime.value) if hasattr(nm, "ExposureTime") else None
        self._gain_db = float(nm.Gain.value) if hasattr(nm, "Gain") else None
        self._channel_exposure = self._read_per_channel("ExposureTime") if self._selectors.get("ExposureTime") else None
        self._channel_gain = self._read_per_channel("Gain") if self._selectors.get("Gain") else None

    def set_exposure(self, exposure_us: tuple[float, ...], gain_db: tuple[float, ...] | None = None) -> None:
        """Write ExposureTime (and Gain) per channel through the selectors, or one value for all."""
        nm = self._nodes()
        for node, values in (("ExposureTime", exposure_us), ("Gain", gain_db)):
            if values is None:
                continue
            if not hasattr(nm, node):
                raise ConfigurationError(f"the camera has no {node} node")
            selectors = self._selectors.get(node)
            if len(values) != len(self.channel_names):
                raise ConfigurationError(f"need one {node} per channel {self.channel_names}, got {list(values)}")
            if not selectors:
                if len(set(values)) > 1:
                    raise ConfigurationError(f"the camera has one {node} for all channels (no selector names "
                                             f"{', '.join(self.channel_names)}), got {list(values)}")
                getattr(nm, node).value = float(values[0])
                continue
            selector = getattr(nm, "ExposureTimeSelector" if node == "ExposureTime" else "GainSelector")
            for entry, value in zip(selectors, values):
                selector.value = entry
                getattr(nm, node).value = float(value)
        self._read_back()

    def start(self) -> None:
        try:
            self._acquirer.start()
        except Exception as exc:
            raise DeviceLost(f"cannot start acquisition: {exc}") from None

    def read(self, timeout_s: float) -> Frame:
        from genicam.gentl import TimeoutException

        try:
            with self._acquirer.fetch(timeout=timeout_s) as buffer:
                received = time.monotonic_ns()
                parts = [decode(c.data_format, component_array(c), c.width, c.height) for c in buffer.payload.components]
                if len(parts) == 1:
                    data, bits = parts[0]
                else:
                    data, bits = assemble_components([p[0] for p in parts]), parts[0][1]
                data = data.copy()  # the buffer goes back to the producer when this block ends
                try:
                    device_ts = int(buffer.timestamp_ns)
                except Exception:  # many producers do not time-stamp buffers
                    device_ts = None
                try:
                    sequence = int(buffer.module.frame_id)
                except Exception:
                    sequence = -1
        except TimeoutException:
            raise FrameTimeout(f"no frame within {timeout_s:g} s") from None
        except (ConfigurationError, FrameTimeout):
            raise
        except Exception as exc:
            raise DeviceLost(f"GenTL acquisition failed: {exc}") from None
        return Frame(data=data, sequence=sequence, host_monotonic_ns=received, wall_time=time.time(),
                     device_timestamp_ns=device_ts, exposure_us=self._exposure_us, gain_db=self._gain_db,
                     channel_names=self.channel_names[: data.shape[-1]], bit_depth=bits,
                     channel_exposure_us=self._channel_exposure, channel_gain_db=self._channel_gain)

    def stop(self) -> None:
        if self._acquirer is not None:
            with contextlib.suppress(Exception):  # a camera that went away stops as best it can
                self._acquirer.stop()

    def close(self) -> None:
        if self._acquirer is not None:
            with contextlib.suppress(Exception):  # likewise its release
                self._acquirer.destroy()
            self._acquirer = None
        if self._harvester is not None:
            self._harvester = None
            _release_harvester(self.producers)
