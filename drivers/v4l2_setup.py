"""Configuring a native V4L2 device for radiometry: format, manual exposure in true units, gain, fixed
white balance, gamma 100; every value read back, every refusal reported with what the camera offers.

Order matters on UVC cameras: the automatic modes are switched off first, because the manual
controls they govern (exposure time, white-balance temperature) are inactive, and may be
refused, while the automatic mode is on.
"""

from __future__ import annotations

from dataclasses import dataclass

from uwcam.drivers.base import CameraSettings, ConfigurationError, ConfigureReport
from uwcam.drivers.pixels import refuse_monochrome
from uwcam.drivers.v4l2_native import (
    CID_AUTO_WHITE_BALANCE,
    CID_BACKLIGHT_COMPENSATION,
    CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO,
    CID_EXPOSURE_AUTO_PRIORITY,
    CID_GAIN,
    CID_GAMMA,
    CID_WHITE_BALANCE_TEMPERATURE,
    DECODABLE,
    EXPOSURE_MANUAL,
    MONOCHROME,
    EXPOSURE_UNIT_US,
    PREFERENCE,
    FormatOffer,
    NativeDevice,
    Refused,
    bit_depth,
    exposure_from_device,
    exposure_to_device,
)

UNITY_GAMMA = 100  # UVC gamma is gamma × 100


@dataclass
class Outcome:
    """What configure did, and what frames are to be labelled with (device read-backs)."""

    report: ConfigureReport
    format: tuple[str, int, int, int, int]
    """(fourcc, width, height, bytes per line, bytes per image) the device chose."""
    exposure_us: float | None
    gain_db: float | None


def _offers(offers: list[FormatOffer]) -> str:
    return "; ".join(str(o) for o in offers) or "nothing"


def choose_format(offers: list[FormatOffer], wanted: str | None, report: ConfigureReport) -> FormatOffer:
    """The offered format to use: the one asked for, else the deepest decodable one offered."""
    by_code = {o.fourcc: o for o in offers}
    if wanted:
        wanted = wanted.strip()
        if wanted in MONOCHROME and wanted in by_code:
            refuse_monochrome(f"Mono{bit_depth(wanted)} ({wanted})")
        if wanted in by_code and wanted in DECODABLE:
            return by_code[wanted]
        if wanted in by_code:
            raise ConfigurationError(
                f"pixel format {wanted} cannot be decoded frame by frame; choose one of "
                f"{', '.join(o.fourcc for o in offers if o.fourcc in DECODABLE) or 'none offered'}"
                + (" (or read the camera's H.264 stream with the 'stream' camera driver)" if wanted.startswith("H26") else ""))
        report.unsupported.append("pixel_format")
        report.details["pixel_format"] = f"{wanted} is not offered; the camera offers {_offers(offers)}"
    for code in PREFERENCE:
        if code in by_code:
            return by_code[code]
    raise ConfigurationError(f"the camera offers no format uwcam can decode: {_offers(offers)}; "
                             f"decodable: {', '.join(sorted(DECODABLE))}")


def choose_size(offer: FormatOffer, current: tuple[int, int], region) -> tuple[int, int]:
    if region is not None:
        return int(region[2]), int(region[3])
    if current in offer.sizes:
        return current
    return max(offer.sizes, key=lambda s: s[0] * s[1]) if offer.sizes else current


class _Setter:
    """Sets one control, reads it back, and files what happened in the report."""

    def __init__(self, dev: NativeDevice, report: ConfigureReport) -> None:
        self.dev, self.report = dev, report
        self.controls = dev.controls()

    def has(self, cid: int) -> bool:
        return cid in self.controls and not self.controls[cid].read_only

    def set(self, cid: int, value: int, name: str) -> int | None:
        """The read-back value, or None (refused: reported under ``name`` with what is offered)."""
        control = self.controls.get(cid)
        if control is None:
            return None
        if control.read_only:
            self.report.details[name] = f"the camera's {control.name} is read-only"
            return None
        if control.menu and value not in control.menu:
            self.report.details[name] = f"{control.name} has no entry {value}; it offers {control.offers()}"
            return None
        try:
            got = self.dev.set(cid, value)
        except Refused as exc:
            self.report.details[name] = f"{control.name} refused {value} ({exc}); it offers {control.offers()}"
            return None
        if got != value:
            self.report.details[name] = (f"{control.name}: asked {value}, the camera set {got}; "
                                         f"it offers {control.offers()}")
        return got


def configure_native(dev: NativeDevice, settings: CameraSettings, *, fourcc: str | None = None,
                     white_balance_k: float | None = None, gain_db_per_step: float | None = None) -> Outcome:
    """Apply ``settings`` to an open native V4L2 device and read everything back."""
    report = ConfigureReport()
    offers = dev.formats()
    offer = choose_format(offers, fourcc or settings.pixel_format, report)
    current = dev.get_format()
    width, height = choose_size(offer, (current[1], current[2]), settings.region)
    if settings.region is not None and (settings.region[0] or settings.region[1]):
        report.unsupported.append("region offset")
        report.details["region offset"] = "V4L2 capture sets the frame size only; crop in processing instead"
    chosen = dev.set_format(offer.fourcc, width, height)
    report.applied["pixel_format"] = chosen[0]
    if chosen[0] != offer.fourcc:
        report.unsupported.append("pixel_format")
        report.details["pixel_format"] = f"asked {offer.fourcc}, the camera gave {chosen[0]}; it offers {_offers(offers)}"
    if (chosen[1], chosen[2]) != (width, height):
        report.unsupported.append("region")
        report.details["region"] = (f"asked {width}×{height}, the camera gave {chosen[1]}×{chosen[2]}; "
                                    f"{offer.fourcc} comes in {', '.join(f'{w}×{h}' for w, h in offer.sizes)}")

    setter = _Setter(dev, report)
    # Automatic modes off first (see the module's docstring).
    if setter.has(CID_EXPOSURE_AUTO):
        if setter.set(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL, "auto exposure") != EXPOSURE_MANUAL:
            report.radiometry_not_disabled.append("auto exposure")
    if setter.has(CID_EXPOSURE_AUTO_PRIORITY):
        setter.set(CID_EXPOSURE_AUTO_PRIORITY, 0, "exposure dynamic frame rate")
    if setter.has(CID_AUTO_WHITE_BALANCE):
        if setter.set(CID_AUTO_WHITE_BALANCE, 0, "auto white balance") != 0:
            report.radiometry_not_disabled.append("auto white balance")
    if setter.has(CID_BACKLIGHT_COMPENSATION):
        low = setter.controls[CID_BACKLIGHT_COMPENSATION].minimum
        if setter.set(CID_BACKLIGHT_COMPENSATION, low, "backlight compensation") != low:
            report.radiometry_not_disabled.append("backlight compensation")
    if setter.has(CID_GAMMA):
        if setter.set(CID_GAMMA, UNITY_GAMMA, "gamma") != UNITY_GAMMA:
            report.radiometry_not_disabled.append("gamma")

    # White balance: fixed at the asked temperature, else at the camera's default.
    if setter.has(CID_WHITE_BALANCE_TEMPERATURE):
        control = setter.controls[CID_WHITE_BALANCE_TEMPERATURE]
        target = int(round(white_balance_k)) if white_balance_k is not None else control.default
        got = setter.set(CID_WHITE_BALANCE_TEMPERATURE, target, "white_balance_k")
        if got is None:
            report.unsupported.append("white_balance_k")
        else:
            report.applied["white_balance_k"] = float(got)
    elif white_balance_k is not None:
        report.unsupported.append("white_balance_k")
        report.details["white_balance_k"] = "the camera has no white_balance_temperature control"

    exposure_us = _exposure(setter, settings.exposure_us, report)
    gain_db = _gain(setter, settings.gain_db, gain_db_per_step, report)

    if settings.frame_rate is not None:
        fps = dev.set_frame_rate(settings.frame_rate)
        if fps is None:
            report.unsupported.append("frame_rate")
        else:
            report.applied["frame_rate"] = fps
            if abs(fps - settings.frame_rate) > 0.01 * settings.frame_rate:
                report.details["frame_rate"] = f"asked {settings.frame_rate:g} frames/s, the camera runs at {fps:g}"
    if settings.black_level is not None:
        report.unsupported.append("black_level")
        report.details["black_level"] = "UVC has no black-level control (brightness is an offset after processing)"
    return Outcome(report, chosen, exposure_us, gain_db)


def _exposure(setter: _Setter, exposure_us: float | None, report: ConfigureReport) -> float | None:
    """Set the exposure time in 100 µs units and return what the device reports, in µs."""
    control = setter.controls.get(CID_EXPOSURE_ABSOLUTE)
    if control is None:
        if exposure_us is not None:
            report.unsupported.append("exposure_us")
            report.details["exposure_us"] = "the camera has no exposure_time_absolute control"
        return None
    if "auto exposure" in report.radiometry_not_disabled:
        return None  # the automatic mode moves the exposure: no value to label frames with
    if exposure_us is None:
        return exposure_from_device(setter.dev.get(CID_EXPOSURE_ABSOLUTE))
    wanted = exposure_to_device(exposure_us)
    got = setter.set(CID_EXPOSURE_ABSOLUTE, wanted, "exposure_us")
    if got is None:
        report.unsupported.append("exposure_us")
        return None
    applied = exposure_from_device(got)
    report.applied["exposure_us"] = applied
    if abs(applied - exposure_us) > 1e-6 * max(1.0, exposure_us):
        report.details["exposure_us"] = (
            f"asked {exposure_us:g} µs, the camera set {applied:g} µs ({got} × {EXPOSURE_UNIT_US:g} µs); it offers "
            f"{exposure_from_device(control.minimum):g}…{exposure_from_device(control.maximum):g} µs in steps of "
            f"{exposure_from_device(control.step):g} µs")
    return applied


def _gain(setter: _Setter, gain_db: float | None, per_step: float | None, report: ConfigureReport) -> float | None:
    """UVC gain counts steps with no unit: its minimum is taken as 0 dB, ``per_step`` dB above it."""
    control = setter.controls.get(CID_GAIN)
    if control is None:
        if gain_db:
            report.unsupported.append("gain_db")
            report.details["gain_db"] = "the camera has no gain control"
        return 0.0 if gain_db == 0 else None

    def in_db(value: int) -> float | None:
        if value == control.minimum:
            return 0.0
        return None if per_step is None else (value - control.minimum) * per_step

    if gain_db is None:
        return in_db(setter.dev.get(CID_GAIN))
    if gain_db != 0 and per_step is None:
        report.unsupported.append("gain_db")
        report.details["gain_db"] = (f"the camera's gain has no unit ({control.offers()}); set the driver option "
                                     "gain_db_per_step from its datasheet or a measurement, or use gain_db: 0")
        return in_db(setter.dev.get(CID_GAIN))
    steps = control.minimum + (int(round(gain_db / per_step)) if gain_db else 0)
    got = setter.set(CID_GAIN, steps, "gain_db")
    if got is None:
        report.unsupported.append("gain_db")
        return None
    report.applied["gain_db"] = in_db(got)
    return in_db(got)
