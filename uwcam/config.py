"""Daemon configuration: a YAML file validated strictly; errors name the file, key and what is expected.

Without a file, ``uwcam run`` uses :func:`default_config`: a simulated camera, lamp and Ping1D
on one simulated vehicle surveying a varied seabed, with a calibration patch in view.

One module, over 500 lines on purpose: it is the whole schema of the YAML a user
writes, section by section, so that every key, its bounds and its default read in one place
(docs/deployment.md shows the file these models validate).
"""

from __future__ import annotations

import ipaddress
import os
import re
from typing import Annotated, Any, Literal

from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator,
                      StrictInt)
from pydantic import Strict as NoCoercion

from uwcam.fileio import UserInputError, explain_validation_error, load_yaml_mapping

CONFIG_VERSION = 1


# Numbers from people and files: finite, never a bool in disguise (``{"intensity": false}``), never
# a string that happens to parse. Every field of every model below uses these.
Real = Annotated[float, NoCoercion(), Field(allow_inf_nan=False)]
"""A finite number (an integer is accepted); NaN, ±Infinity, booleans and strings are refused."""
Whole = Annotated[int, NoCoercion()]
"""An integer; booleans, floats and strings are refused."""
Flag = Annotated[bool, NoCoercion()]
"""true or false only; 0/1 and strings are refused."""
Pixel = Annotated[Whole, Field(ge=0, le=1 << 16)]
"""A pixel coordinate."""
Extent = Annotated[Whole, Field(gt=0, le=1 << 16)]
"""A width or height in pixels."""
Box = tuple[Pixel, Pixel, Extent, Extent]
"""x, y, width, height in pixels."""


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class CameraSettingsConfig(Strict):
    exposure_us: Annotated[Real, Field(gt=0, le=1e8)] | None = None
    """Microseconds."""
    gain_db: Annotated[Real, Field(ge=-100, le=100)] | None = None
    pixel_format: str | None = None
    region: Box | None = None
    black_level: Annotated[Real, Field(ge=0, le=1e6)] | None = None
    frame_rate: Annotated[Real, Field(gt=0, le=10000)] | None = None


class CameraConfig(Strict):
    driver: str = "sim"
    """Registry name: sim, replay, genicam, aravis, v4l2, multi, or a plug-in's."""
    options: dict[str, Any] = {}
    """Passed to the driver (e.g. cti, serial_number, device)."""
    settings: CameraSettingsConfig = CameraSettingsConfig()
    # The loop always takes the newest frame, so older queued frames are skipped anyway: a deep
    # queue only holds memory (12 MB per 1080p 16-bit frame).
    queue_size: Annotated[Whole, Field(ge=1, le=64)] = 2
    watchdog_s: Annotated[Real, Field(gt=0, le=3600)] = 2.0


class DeviceConfig(Strict):
    driver: str
    options: dict[str, Any] = {}


class MarkerConfig(Strict):
    """An OpenCV ArUco marker beside the patch, found every frame, that places the patch region."""

    dictionary: str = "DICT_4X4_50"
    """OpenCV predefined dictionary name."""
    id: Annotated[Whole, Field(ge=0, le=100000)]
    offset: tuple[Annotated[Real, Field(ge=-1000, le=1000)], Annotated[Real, Field(ge=-1000, le=1000)]]
    """From the marker's top-left corner to the patch region's, in marker side lengths (x, y)."""
    size: tuple[Annotated[Real, Field(gt=0, le=1000)], Annotated[Real, Field(gt=0, le=1000)]]
    """Patch region width and height in marker side lengths."""

    @model_validator(mode="after")
    def _known_dictionary(self) -> "MarkerConfig":
        import cv2

        if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary '{self.dictionary}'; e.g. DICT_4X4_50, DICT_6X6_250")
        return self


class PatchConfig(Strict):
    """A calibration patch fixed in view for live tracking of attenuation differences (docs/physics.md §6)."""

    region: Box | None = None
    """x, y, width, height in pixels, for a patch fixed in the image."""
    marker: MarkerConfig | None = None
    """Or: find the patch every frame next to a fiducial marker (the vehicle flexes, the bracket moves)."""
    path_length_m: Annotated[Real, Field(gt=0, le=1000)]
    """Lamp → patch → camera path length d_T^p, metres."""
    smoothing: Annotated[Real, Field(gt=0, le=1)] = 0.1
    """EMA weight of each new estimate."""
    max_step: Annotated[Real, Field(gt=0, le=100)] = 0.05
    """Estimates further than this (1/m) from the tracked value are rejected as outliers."""

    @model_validator(mode="after")
    def _one_way_to_find_it(self) -> "PatchConfig":
        if (self.region is None) == (self.marker is None):
            raise ValueError("a patch needs either a fixed 'region' or a 'marker' that locates it, not both")
        return self


class ReflectanceConfig(Strict):
    """Surface reflectance from the rangefinder (docs/physics.md §8): where its beam meets the scene in
    the image, and how fresh a reading must be to use it."""

    footprint: Box
    """x, y, width, height in pixels of the rangefinder's footprint."""
    max_age_s: Annotated[Real, Field(gt=0, le=3600)] = 0.5
    """Readings further than this from the frame's capture time are not used."""
    smoothing: Annotated[Real, Field(gt=0, le=1)] = 0.2
    """EMA weight of each new estimate of the surface's log constants."""
    tolerance: Annotated[Real, Field(gt=0, le=10)] = 0.002
    """Change in log constants (natural-log units) below which the estimator is not rebuilt."""


class BackscatterConfig(Strict):
    """Backscatter subtracted in the frame loop (docs/physics.md §5), from the calibration's
    black-patch measurements and an open-water frame when one was taken."""

    iterations: Annotated[Whole, Field(ge=1, le=5)] = 2
    """Range → backscatter at that range → subtract → range, this many times per frame."""


class OrientationConfig(Strict):
    """Surface incidence angles by Kirlin's multichannel Gauss–Newton step (docs/physics.md §9),
    per block of pixels, seeded with the fused range. Needs the profile's absolute attenuations and
    an absolute scale measured at the rangefinder's footprint (``reflectance``)."""

    block: Annotated[Whole, Field(ge=4, le=128)] = 16
    """Side of the square pixel blocks whose mean irradiance and range enter one Gauss–Newton solve."""
    iterations: Annotated[Whole, Field(ge=1, le=50)] = 8
    """Gauss–Newton steps per frame at most."""
    beam_half_angle_deg: Annotated[Real, Field(gt=0, le=180)] | None = None
    """The lamp's beam pattern exp(−k(1 − cos θ)) with half power at this angle off its axis
    (the camera's z axis); None: a uniform beam."""


class ExposureConfig(Strict):
    """The radiometric exposure controller (uwcam.runtime.stages.exposure; docs/exposure.md): per channel where
    the camera allows, one exposure otherwise. Never the camera's own auto-exposure."""

    target: Annotated[Real, Field(gt=0.05, le=0.98)] = 0.8
    """Each channel's high percentile is brought to this fraction of the saturation level."""
    high_percentile: Annotated[Real, Field(ge=50, le=100)] = 99.5
    """Percentile of a channel's raw values that stands for its brightest useful pixels."""
    low_percentile: Annotated[Real, Field(ge=0, lt=50)] = 10.0
    """Percentile that stands for its weakest useful pixels, checked against the noise floor."""
    min_exposure_us: Annotated[Real, Field(gt=0, le=1e8)] = 10.0
    max_exposure_us: Annotated[Real, Field(gt=0, le=1e8)] = 100000.0
    """Longest exposure (µs): at 30 frames/s no more than 33 000 keeps the frame rate."""
    max_step: Annotated[Real, Field(gt=1, le=100)] = 2.0
    """Largest change of a channel's exposure from one frame to the next (a factor)."""
    tolerance: Annotated[Real, Field(ge=0, lt=1)] = 0.1
    """Dead band: a wanted change smaller than this fraction is not made."""
    hdr: Flag = True
    """On a camera with one exposure for all channels: alternate a short and a long exposure and
    merge consecutive frames per channel (uwcam.runtime.stages.hdr); false: one exposure, the strongest channel's."""

    @model_validator(mode="after")
    def _limits(self) -> "ExposureConfig":
        if self.min_exposure_us >= self.max_exposure_us:
            raise ValueError("min_exposure_us must be less than max_exposure_us")
        return self


class TemporalConfig(Strict):
    """Temporal fusion in the loop (uwcam.runtime.stages.temporal; docs/physics.md §11): a running
    per-pixel mean of the frames over which the scene held still, ranged as one frame with its
    noise divided accordingly. A pixel starts afresh where the new frame differs from the mean by
    more than its noise allows, where it is saturated, and everywhere when the exposure changes.

    Off by default (``processing.temporal`` null): the embedded default is a vehicle surveying at
    0.4 m/s, whose view shifts several pixels a frame, so nearly every pixel would start afresh
    every frame and fusion would cost time for nothing; a pilot holding station at an inspection
    target switches it on (the page's switch, or PATCH /api/v1/config {"temporal": {}})."""

    max_frames: Annotated[Whole, Field(ge=2, le=1024)] = 32
    """Most frames one pixel's estimate is built from: beyond it each new frame weighs 1/max_frames
    (a running average), so the estimate follows slow drift (tide, a settling vehicle) within
    about max_frames frames; at 30 frames/s, 32 is about a second."""
    change_sigmas: Annotated[Real, Field(ge=2, le=100)] = 4.0
    """A pixel starts afresh when any channel of the new frame differs from the running mean by more
    than this many standard deviations of that difference (the noise model's frame-to-frame noise).
    At 4 a still pixel of three channels starts afresh by chance about once in 5000 frames."""
    motion_pixels: Annotated[Real, Field(gt=0, le=10000)] | None = 0.5
    """Where the autopilot reports the vehicle's motion over MAVLink (ATTITUDE's rates,
    LOCAL_POSITION_NED's velocity; needs the ``mavlink`` section): every pixel starts afresh when
    that motion over one frame interval moves the image by more than this many pixels (turning:
    f·ω·Δt; moving: f·v·Δt over the median range), before a change too slow for the noise to show
    is averaged in. None: motion is judged from the image alone."""


class ProcessingConfig(Strict):
    pair: tuple[str, str] | None = None
    """Two channel names for single-pair ranging; None fuses all channels."""
    smoothing: Literal["none", "mean", "median", "adaptive"] = "none"
    """3×3 smoothing ("mean", "median"), or windows that adapt to the signal ("adaptive"): a pixel whose σ
    is above ``smoothing_target`` × its range, or that has no range for too little light, is ranged
    from the mean light of the smallest window (3, 5, 9 or 17 pixels a side) that reaches the target,
    given up at a range step larger than a few single-pixel σ; the others keep their own (docs/physics.md §7)."""
    smoothing_stage: Literal["after", "before"] = "after"
    """Smooth the range map (after; keeps edges of invalid areas) or the image (before the transform);
    3×3 mean and median only (adaptive windows average the image and judge by the range)."""
    smoothing_target: Annotated[Real, Field(ge=0.001, le=0.5)] = 0.02
    """Adaptive smoothing's target: σ as a fraction of the range (0.02: 2 %), from 0.001 to 0.5."""
    path_length_bounds: tuple[Annotated[Real, Field(ge=0, le=10000)], Annotated[Real, Field(gt=0, le=10000)]] = (0.0, 100.0)
    """Accepted lamp → surface → camera path lengths [min, max], metres."""
    patch: PatchConfig | None = None
    lamp_off_interval: Annotated[Whole, Field(ge=0, le=100000)] = 0
    """Every this many frames, take one with the lamp off and subtract it (daylight, dark level)
    from the lamp-lit frames that follow; 0: never."""
    reflectance: ReflectanceConfig | None = None
    """Correct for the surface's hue with the rangefinder; None: assume the calibration target's hue."""
    backscatter: BackscatterConfig | None = None
    """Subtract the water's own light (backscatter) in the loop; None: do not."""
    orientation: OrientationConfig | None = None
    """Surface incidence angles (Kirlin) in the loop; None: off."""
    exposure: ExposureConfig | None = None
    """Radiometric exposure control, per channel where the camera allows; None: the exposure stays as set."""
    temporal: TemporalConfig | None = None
    """Fuse frames over time where the scene holds still (√N less noise holding station); None: off."""
    vehicle_mask: Annotated[list[Box], Field(max_length=64)] = []
    """Regions (x, y, width, height in pixels) where the vehicle itself is in view: the patch's
    bracket, skids, a manipulator. They get no range (reason 6, "vehicle"), so that the page's
    minimum range, MAVLink obstacles and point clouds never take the vehicle for an obstacle."""

    @model_validator(mode="after")
    def _bounds(self) -> "ProcessingConfig":
        if self.path_length_bounds[0] >= self.path_length_bounds[1]:
            raise ValueError("path_length_bounds must be [min, max] with min < max")
        return self


class ApiConfig(Strict):
    host: Annotated[str, Field(min_length=1)] = "127.0.0.1"
    """Address to listen on; only explicit loopback addresses (127.0.0.1, ::1, localhost) count as
    loopback, and any other needs a token."""
    port: Annotated[Whole, Field(ge=0, le=65535)] = 8080
    token: str | None = None
    """Bearer token for endpoints that change state; required when listening beyond loopback.
    Also read from the UWCAM_TOKEN environment variable."""
    stream_rate_hz: Annotated[Real, Field(gt=0, le=120)] = 30.0
    """Most frames per second sent to one WebSocket client."""
    allowed_hosts: list[Annotated[str, Field(min_length=1)]] = []
    """Host names (``*.example.org`` patterns allowed) by which the daemon may be reached besides
    IP addresses, localhost and ``*.local``; others are refused to defeat DNS rebinding."""
    allowed_origins: list[Annotated[str, Field(pattern=r"^https?://[^/\s]+$")]] = []
    """Web origins (``http://host:port``) besides the daemon's own whose pages may change state
    and call the API from the browser (CORS), e.g. Cockpit served from another port; and that
    may show uwcam's pages in a frame."""
    cockpit_actions_token: Flag = False
    """Put the API token into the lamp actions of ``/cockpit_extras.json`` so that Cockpit's
    actions are authorised. Anyone who can reach the daemon can read that document, so set this
    only where they could read the token anyway: on BlueOS, whose terminal and file browser
    (the token file included) are open to the vehicle's network. Off: the actions carry no token
    and get 401 while a token is set (add the header in Cockpit's action editor)."""


FiniteFloat = Real
"""Kept for the sections written before :data:`Real`: the same strict finite number."""


class RecordingConfig(Strict):
    """MCAP recordings of dives (raw frames, range results, status); see docs/recording.md."""

    folder: Annotated[str, Field(min_length=1)] = "recordings"
    """Where recordings started from the API go, named by their start time (UTC)."""
    start_file: Annotated[str, Field(min_length=1)] | None = None
    """Record into this .mcap file from start to stop (what ``uwcam run --record FILE`` sets)."""
    max_size_mb: Annotated[FiniteFloat, Field(gt=0, le=1e7)] | None = 4000.0
    """Start a new file (rotation) when one reaches this size in megabytes; None: no limit."""
    max_duration_s: Annotated[FiniteFloat, Field(gt=0, le=1e7)] | None = None
    """Start a new file when one has recorded this long; None: no limit."""
    queue_frames: Annotated[Whole, Field(ge=1, le=10000)] = 32
    """Frames waiting for the disk; beyond this the oldest is dropped and counted."""
    queue_mb: Annotated[FiniteFloat, Field(gt=0, le=1e6)] = 128.0
    """Most megabytes of frames (raw frame, range, variance, reasons) waiting for the disk: at
    1920×1080 a frame and its results are 31 MB, so this, not queue_frames, bounds the memory
    a slow disk can take; beyond it the oldest is dropped and counted."""
    results: Flag = False
    """Record each ranged frame's depth, variance and reasons too (19 MB of a 1920×1080 16-bit
    frame's 31 MB, 560 MB/s at 30 frames/s). False (the default): the raw frames with their
    metadata, the ranging records and the ambient light only, from which ``uwcam reprocess``
    makes depth, variance and reasons bit for bit."""
    budget_mb_s: Annotated[FiniteFloat, Field(gt=0, le=100000)] | None = 40.0
    """Most megabytes a second the recording writes on average (a 2-second burst allowed): raw
    frames beyond it are decimated, evenly, and counted (``frames_decimated``); every frame's
    metadata and ranging record and the previews are always kept. 40 MB/s is 144 GB an hour;
    raw 16-bit frames at 30 frames/s are 166 MB/s at 1280×720 and 373 MB/s at 1920×1080, and
    lossless compression gains only 2–25 % on sensor noise (docs/recording.md). None: no budget."""
    compression: Literal["lz4", "zstd", "none"] = "lz4"
    """Compression of each MCAP chunk. lz4 costs little more than a copy; zstd makes files about
    a third smaller but costs ~9× the CPU (~140 MB/s on one core here: it drops frames beyond
    about 720p at 10 fps); none only copies."""
    chunk_kb: Annotated[FiniteFloat, Field(ge=16, le=65536)] = 1024
    """MCAP chunk size: a crash loses at most the chunk being filled; reprocessing splits at chunks."""
    status_interval_s: Annotated[FiniteFloat, Field(gt=0, le=3600)] = 1.0
    """How often the daemon's status is written into the recording."""
    preview_rate_hz: Annotated[FiniteFloat, Field(ge=0, le=60)] = 2.0
    """Colour previews per second on ``/uwcam/image/preview`` (foxglove.CompressedImage, JPEG,
    display-stretched like the operator page, half resolution): what Foxglove draws, since it
    cannot draw the 16-bit raw frames. 0: none."""
    preview_quality: Annotated[Whole, Field(ge=1, le=100)] = 80
    """JPEG quality of the previews."""


class MountingConfig(Strict):
    """Where the camera sits on the vehicle: the transform from the vehicle's frame to the
    camera's (x right, y down, z forward, the frame ``uwcam_camera`` of every recorded image),
    recorded as foxglove.FrameTransform so that Foxglove places images and points on the vehicle."""

    parent_frame: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_./-]+$")] = "base_link"
    """The vehicle's frame, e.g. base_link (ROS REP 103: x forward, y left, z up)."""
    translation_m: tuple[Annotated[FiniteFloat, Field(ge=-100, le=100)], Annotated[FiniteFloat, Field(ge=-100, le=100)],
                         Annotated[FiniteFloat, Field(ge=-100, le=100)]] = (0.0, 0.0, 0.0)
    """The camera's optical centre in the vehicle's frame, metres."""
    rotation_deg: tuple[Annotated[FiniteFloat, Field(ge=-360, le=360)], Annotated[FiniteFloat, Field(ge=-360, le=360)],
                        Annotated[FiniteFloat, Field(ge=-360, le=360)]] = (-90.0, 0.0, -90.0)
    """Roll, pitch, yaw in degrees of the camera's frame in the vehicle's, as ROS gives them: the
    camera's axes are the columns of Rz(yaw)·Ry(pitch)·Rx(roll). The default, (−90, 0, −90), is a
    camera looking forward (its z along the vehicle's x); (180, 0, −90) looks down with the top of
    the image toward the bow."""


class FoxgloveConfig(Strict):
    """Live view in Foxglove over its WebSocket protocol (opt-in; see docs/recording.md)."""

    enabled: Flag = False
    host: Annotated[str, Field(min_length=1)] = "127.0.0.1"
    """Address to listen on; the protocol has no authentication, so keep it on a trusted network."""
    port: Annotated[Whole, Field(ge=0, le=65535)] = 8765
    rate_hz: Annotated[FiniteFloat, Field(gt=0, le=120)] = 10.0
    """Most frames per second sent."""
    point_stride: Annotated[Whole, Field(ge=1, le=64)] = 2
    """Every this many pixels in x and y becomes a point of the point cloud."""


ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream")
"""The Zenoh link protocols an endpoint may name: ``<protocol>/<host>:<port>``, or
``unixsock-stream/<path>``; Zenoh's ``?metadata`` and ``#config`` may follow."""
_PORT = r"(?:6553[0-5]|655[0-2][0-9]|65[0-4][0-9]{2}|6[0-4][0-9]{3}|[1-5][0-9]{4}|[1-9][0-9]{0,3})"
"""1–65535, without leading zeros."""
_HOST = r"(?:\[[0-9A-Fa-f:.]+(?:%[A-Za-z0-9_.-]+)?\]|[A-Za-z0-9][A-Za-z0-9.-]*)"
"""An [IPv6] address (a zone allowed), an IPv4 address or a host name."""
_ZENOH_ENDPOINT = re.compile(r"^(?:(?:tcp|udp|tls|quic|ws)/" + _HOST + ":" + _PORT + r"|unixsock-stream/[^\s?#]+)"
                             r"(?:\?[^\s#]*)?(?:#\S*)?$")
"""A whole Zenoh endpoint, its port within 1–65535 (uwcam monitor checks its options with it too)."""
_ENDPOINT_PARTS = re.compile(r"^(?P<protocol>[^/\s]*)/(?P<address>[^?#]*)")
_KEY_SEGMENT = re.compile(r"^[A-Za-z0-9_.~+-]+$")


def check_zenoh_endpoint(endpoint: str) -> str:
    """``endpoint`` if Zenoh can open it (a known protocol, a host and a port 1–65535); else
    ValueError saying which part is wrong. Checked here, so that ``uwcam config check`` finds
    what would otherwise stop ``uwcam run`` when Zenoh opens its session."""
    example = "e.g. tcp/192.168.2.1:7447"
    parts = _ENDPOINT_PARTS.match(endpoint)
    if _ZENOH_ENDPOINT.match(endpoint):
        host = parts["address"].rpartition(":")[0]
        if parts["protocol"] != "unixsock-stream" and (host.startswith("[") or re.fullmatch(r"[0-9.]+", host)):
            try:  # an address, not a name: one Zenoh can bind or reach
                ipaddress.ip_address(host.strip("[]"))
            except ValueError:
                raise ValueError(f"'{endpoint}': {host} is not an IP address; {example}") from None
        return endpoint
    if parts is None or parts["protocol"] not in ZENOH_PROTOCOLS:
        raise ValueError(f"'{endpoint}' is not a Zenoh endpoint <protocol>/<host>:<port> with a protocol of "
                         f"{', '.join(ZENOH_PROTOCOLS)}; {example}")
    host, _, port = parts["address"].rpartition(":")
    if parts["protocol"] != "unixsock-stream" and host and port.isdigit() and not 1 <= int(port) <= 65535:
        raise ValueError(f"'{endpoint}': port {int(port)} is not 1–65535; {example}")
    raise ValueError(f"'{endpoint}' is not a Zenoh endpoint <protocol>/<host>:<port> (port 1–65535); {example}")


ZenohEndpoint = Annotated[str, AfterValidator(check_zenoh_endpoint)]
"""A Zenoh endpoint, checked by :func:`check_zenoh_endpoint`."""


class ZenohConfig(Strict):
    """Publish status, range summaries, previews and device health on Zenoh for remote monitoring
    (opt-in; see docs/api.md, "Zenoh"). Read-only: nothing is changed over Zenoh."""

    mode: Literal["peer", "client"] = "peer"
    """peer: talk to other peers directly (and listen); client: go through a Zenoh router."""
    listen: list[ZenohEndpoint] = []
    """Endpoints to listen on, e.g. tcp/0.0.0.0:7447; empty: Zenoh's default for the mode."""
    connect: list[ZenohEndpoint] = []
    """Endpoints to connect to, e.g. tcp/192.168.2.1:7447 (a router, or the topside peer)."""
    scouting: Flag = True
    """Multicast scouting: find peers and routers on the LAN without endpoints."""
    key_prefix: Annotated[str, Field(min_length=1, max_length=200)] | None = None
    """Keys are published under this, e.g. uwcam/rov1; None: uwcam/<host name>."""
    budget_kbit_s: Annotated[Real, Field(ge=1, le=1e6)] = 256.0
    """Most kilobits per second of payload this vehicle publishes: previews shrink and slow to fit;
    status, health and range summaries never stop."""
    preview_rate_hz: Annotated[Real, Field(gt=0, le=30)] = 1.0
    """Most previews per second (fewer when the budget does not allow)."""
    preview_width: Annotated[Whole, Field(ge=16, le=1920)] = 160
    """Width of the previews in pixels at most (smaller when the budget does not allow)."""
    preview_quality: Annotated[Whole, Field(ge=10, le=100)] = 70
    """JPEG quality of the colour preview."""
    page_url: Annotated[str, Field(pattern=r"^https?://[^\s]+$", max_length=500)] | None = None
    """Where this vehicle's own page is reachable from topside (e.g. http://192.168.2.2:8080/):
    published in ``status`` so that the fleet view (``uwcam monitor``) links to it; None: no link."""

    @field_validator("key_prefix")
    @classmethod
    def _prefix(cls, v: str | None) -> str | None:
        if v is not None and not all(_KEY_SEGMENT.match(part) for part in v.split("/")):
            raise ValueError(f"key_prefix '{v}' must be words of letters, digits and _.~+- separated by single "
                             "slashes, without wildcards (* $ ? #) or a leading/trailing slash, e.g. uwcam/rov1")
        return v


class RangeAlertConfig(Strict):
    """Collision warning: the minimum range (m, the smallest median over small tiles of the range
    map, as the Zenoh range summary gives it) below ``below_m`` for ``for_s`` seconds."""

    below_m: Annotated[Real, Field(gt=0, le=1000)]
    """Metres of camera range along the ray."""
    for_s: Annotated[Real, Field(ge=0, le=3600)] = 1.0


class DeviceAlertConfig(Strict):
    """A device (camera, lamp, rangefinder) lost or recovering for more than ``for_s`` seconds."""

    for_s: Annotated[Real, Field(ge=0, le=86400)] = 10.0


class CalibrationAlertConfig(Strict):
    """The calibration in use is old, or the attenuation the calibration patch tracks has drifted
    beyond the calibration's own uncertainty."""

    max_age_days: Annotated[Real, Field(gt=0, le=36500)] | None = 90.0
    """Days since the profile was made (its provenance); None: no age alert."""
    drift_sigmas: Annotated[Real, Field(gt=0, le=1000)] | None = 3.0
    """Alert when a channel's tracked attenuation difference is more than this many of the
    profile's standard uncertainties (attenuation_difference_std) from the calibrated one, for
    ``drift_for_s``; channels without an uncertainty are not judged. None: no drift alert."""
    drift_for_s: Annotated[Real, Field(ge=0, le=86400)] = 30.0


class FramesDroppedAlertConfig(Strict):
    """More than ``above_percent`` of the frames the camera delivered over the last ``window_s``
    seconds were dropped (camera queue full, or skipped for a newer frame)."""

    above_percent: Annotated[Real, Field(ge=0, lt=100)]
    window_s: Annotated[Real, Field(ge=2, le=3600)] = 30.0


class AlertsConfig(Strict):
    """Alerts: each raised once when its condition has held long enough, cleared once when it has
    ended for ``clear_s``; shown on the page, at GET /api/v1/alerts, on Zenoh ``alerts`` and as
    MAVLink STATUSTEXT (docs/api.md, "Alerts"). A rule set to null is off."""

    enabled: Flag = True
    range: RangeAlertConfig | None = None
    """Off by default: the distance that means danger depends on the vehicle."""
    device: DeviceAlertConfig | None = DeviceAlertConfig()
    calibration: CalibrationAlertConfig | None = None
    """Off by default: how long a calibration stays good depends on the water and the crew."""
    disk_free_below_percent: Annotated[Real, Field(gt=0, le=100)] | None = 5.0
    """Free space on the disk recordings go to below this share of its size."""
    frames_dropped: FramesDroppedAlertConfig | None = None
    """Off by default: on a busy computer skipping frames for newer ones is normal."""
    clear_s: Annotated[Real, Field(ge=0, le=3600)] = 2.0
    """An alert clears once its condition has been false this long (no flapping at a threshold)."""
    history: Annotated[Whole, Field(ge=1, le=10000)] = 100
    """Raised and cleared events kept for GET /api/v1/alerts."""


# MAV_SENSOR_ORIENTATION names (MAVLink common.xml) the MAVLink output accepts, by value. CUSTOM
# (100) is left out: it needs a quaternion, which uwcam does not know.
SENSOR_ORIENTATIONS = {
    "NONE": 0, "YAW_45": 1, "YAW_90": 2, "YAW_135": 3, "YAW_180": 4, "YAW_225": 5, "YAW_270": 6, "YAW_315": 7,
    "ROLL_180": 8, "ROLL_180_YAW_45": 9, "ROLL_180_YAW_90": 10, "ROLL_180_YAW_135": 11, "PITCH_180": 12,
    "ROLL_180_YAW_225": 13, "ROLL_180_YAW_270": 14, "ROLL_180_YAW_315": 15, "ROLL_90": 16, "ROLL_90_YAW_45": 17,
    "ROLL_90_YAW_90": 18, "ROLL_90_YAW_135": 19, "ROLL_270": 20, "ROLL_270_YAW_45": 21, "ROLL_270_YAW_90": 22,
    "ROLL_270_YAW_135": 23, "PITCH_90": 24, "PITCH_270": 25, "PITCH_180_YAW_90": 26, "PITCH_180_YAW_270": 27,
    "ROLL_90_PITCH_90": 28, "ROLL_180_PITCH_90": 29, "ROLL_270_PITCH_90": 30, "ROLL_90_PITCH_180": 31,
    "ROLL_270_PITCH_180": 32, "ROLL_90_PITCH_270": 33, "ROLL_180_PITCH_270": 34, "ROLL_270_PITCH_270": 35,
    "ROLL_90_PITCH_180_YAW_90": 36, "ROLL_90_YAW_270": 37, "ROLL_90_PITCH_68_YAW_293": 38, "PITCH_315": 39,
    "ROLL_90_PITCH_315": 40,
}
_CONNECTION = re.compile(r"^(?:(?P<scheme>udpout|tcp):(?P<host>\[[0-9A-Fa-f:.]+\]|[^:\s\[\]]+):(?P<port>\d{1,5})"
                         r"|(?P<device>/\S+))$")


def parse_mavlink_connection(text: str) -> tuple[str, str, int]:
    """``udpout:HOST:PORT`` → ("udpout", host, port); ``tcp:HOST:PORT`` → ("tcp", host, port);
    a serial device path → ("serial", path, 0). ValueError says which forms are accepted."""
    m = _CONNECTION.match(text)
    if m is None:
        raise ValueError(f"connection '{text}' is not udpout:HOST:PORT, tcp:HOST:PORT or a serial device path "
                         "such as /dev/ttyACM0")
    if m["device"]:
        return "serial", m["device"], 0
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise ValueError(f"connection '{text}': port {port} is not 1–65535")
    return m["scheme"], m["host"].strip("[]"), port


class MavlinkConfig(Strict):
    """Range to an autopilot (ArduSub, PX4) as MAVLink DISTANCE_SENSOR, and optionally
    OBSTACLE_DISTANCE, with a HEARTBEAT at 1 Hz (see docs/mavlink.md)."""

    connection: Annotated[str, Field(min_length=1)] = "udpout:127.0.0.1:14550"
    """udpout:HOST:PORT, tcp:HOST:PORT or a serial device path (/dev/ttyACM0)."""
    baud: Annotated[Whole, Field(ge=1200, le=4_000_000)] = 115200
    """Baud rate when ``connection`` is a serial device."""
    source_system: Annotated[Whole, Field(ge=1, le=255)] = 1
    """MAVLink system id to send as: the vehicle's (ArduSub's SYSID_THISMAV, 1 by default)."""
    source_component: Annotated[Whole, Field(ge=1, le=255)] = 158
    """MAVLink component id to send as; 158 is MAV_COMP_ID_PERIPHERAL."""
    rate_hz: Annotated[Real, Field(gt=0, le=50)] = 10.0
    """DISTANCE_SENSOR (and OBSTACLE_DISTANCE) messages per second; ArduPilot drops a MAVLink
    rangefinder after 500 ms without one."""
    region: tuple[Annotated[Whole, Field(ge=0)], Annotated[Whole, Field(ge=0)], Annotated[Whole, Field(gt=0)],
                  Annotated[Whole, Field(gt=0)]] | None = None
    """x, y, width, height in pixels whose valid ranges make the distance; None: the whole image."""
    statistic: Literal["median", "minimum"] = "median"
    """median (altitude over a seabed) or minimum (nearest obstacle, forward-looking)."""
    minimum_block: Annotated[Whole, Field(ge=1, le=64)] = 8
    """The "minimum" is the smallest median over square tiles of this many pixels a side (at
    least half of them valid), so that single noisy pixels do not set it; 1 takes the smallest
    pixel."""
    min_valid_fraction: Annotated[Real, Field(gt=0, le=1)] = 0.05
    """Below this fraction of valid pixels in the region nothing is sent."""
    max_age_s: Annotated[Real, Field(gt=0, le=10)] = 0.5
    """Nothing is sent while the newest processed frame is older than this (seconds)."""
    orientation: str | StrictInt = "PITCH_270"
    """MAV_SENSOR_ORIENTATION name (with or without MAV_SENSOR_ROTATION_) or number, as ArduPilot's
    RNGFNDx_ORIENT takes it: PITCH_270 (25) looks down, NONE (0) forward; it must equal the
    autopilot's RNGFNDx_ORIENT. Kept as the name."""
    sensor_id: Annotated[Whole, Field(ge=0, le=255)] = 0
    """DISTANCE_SENSOR ``id``, distinct from the vehicle's other rangefinders."""
    obstacle_distance: Flag = False
    """Also send OBSTACLE_DISTANCE: 72 sectors across the camera's whole horizontal field of view
    (over the rows of ``region``), for a camera looking horizontally (orientation NONE or YAW_*)."""

    @model_validator(mode="after")
    def _check(self) -> "MavlinkConfig":
        parse_mavlink_connection(self.connection)
        if isinstance(self.orientation, int):
            names = {v: k for k, v in SENSOR_ORIENTATIONS.items()}
            if self.orientation not in names:
                raise ValueError(f"unknown orientation number {self.orientation}; MAV_SENSOR_ORIENTATION numbers are "
                                 f"{min(names)}–{max(names)}, e.g. 25 (PITCH_270, down) or 0 (NONE, forward)")
            self.orientation = names[self.orientation]
        name = self.orientation.upper().removeprefix("MAV_SENSOR_ROTATION_")
        if name.isdigit():  # a number written as a string: "25"
            self.orientation = int(name)
            return self._check()
        if name not in SENSOR_ORIENTATIONS:
            raise ValueError(f"unknown orientation '{self.orientation}'; e.g. PITCH_270 or 25 (down), NONE or 0 "
                             "(forward), YAW_90 or 2 (right), PITCH_90 or 24 (up)")
        self.orientation = name
        if self.obstacle_distance and SENSOR_ORIENTATIONS[name] > 7:
            raise ValueError(f"obstacle_distance needs a camera looking horizontally (orientation NONE or YAW_*), "
                             f"not {name}")
        return self

    @property
    def orientation_value(self) -> int:
        return SENSOR_ORIENTATIONS[self.orientation]


class DaemonConfig(Strict):
    version: Literal[1] = CONFIG_VERSION
    camera: CameraConfig = CameraConfig()
    lamp: DeviceConfig | None = None
    rangefinder: DeviceConfig | None = None
    mounting: MountingConfig | None = None
    """The camera's place on the vehicle, recorded as a transform; None: no transform recorded."""
    calibration: str | None = None
    """Path of the calibration profile; None only with the simulated camera (calibrated at start)."""
    profiles_dir: str | None = None
    """Folder of calibration profiles (*.yaml): loaded at start, and where uploads are saved."""
    state_dir: str | None = None
    """Folder for state that survives a restart (live processing settings, active profile, lamp
    intensity); default: the profiles folder. With neither, nothing is kept across restarts."""
    simulation: dict[str, Any] = {}
    """Options of the shared simulated rig (scene, distance, size, water, lamp_offset, speed,
    altitude...) when devices are simulated; see uwcam.simulation.options."""
    processing: ProcessingConfig = ProcessingConfig()
    api: ApiConfig = ApiConfig()
    mavlink: MavlinkConfig | None = None
    """Send range to an autopilot over MAVLink; None: no MAVLink output."""
    recording: RecordingConfig = RecordingConfig()
    foxglove: FoxgloveConfig = FoxgloveConfig()
    zenoh: ZenohConfig | None = None
    """Publish for remote monitoring on Zenoh (needs ``pip install 'uwcam[zenoh]'``); None: off."""
    alerts: AlertsConfig = AlertsConfig()
    """Alert rules (collision warning, devices down, calibration age and drift, disk, dropped frames)."""

    @field_validator("simulation")
    @classmethod
    def _simulation(cls, v: dict[str, Any]) -> dict[str, Any]:
        from uwcam.simulation.options import check_simulation_options

        return check_simulation_options(v)

    @model_validator(mode="after")
    def _calibration_needed(self) -> "DaemonConfig":
        from uwcam.drivers.registry import known

        # An unknown driver first: asking for a calibration of a camera uwcam cannot drive misleads.
        for kind, device in (("camera", self.camera), ("lamp", self.lamp), ("rangefinder", self.rangefinder)):
            if device is not None and device.driver not in known(kind):
                raise ValueError(f"{kind}.driver: unknown {kind} driver '{device.driver}'; known {kind} drivers: "
                                 f"{', '.join(known(kind))}")
        if self.calibration is None and self.camera.driver != "sim":
            raise ValueError("calibration: give the path of a calibration profile (uwcam calibrate makes one)")
        if self.processing.lamp_off_interval and self.lamp is None:
            raise ValueError("processing.lamp_off_interval needs a lamp: configure one or set it to 0")
        if self.processing.reflectance is not None and self.rangefinder is None:
            raise ValueError("processing.reflectance needs a rangefinder: configure one or remove it")
        return self


def load_config(path: str | os.PathLike[str]) -> DaemonConfig:
    """Load and validate; UserInputError names the file, the key path and what is wrong."""
    data = load_yaml_mapping(path, "configuration")
    try:
        return DaemonConfig.model_validate(data)
    except ValidationError as exc:
        raise UserInputError(explain_validation_error(exc, f"configuration {path}")) from None


def default_config() -> DaemonConfig:
    """The embedded default: a simulated vehicle surveying a varied seabed at 1280×720, 30 fps
    (its altitude rising and falling between 1.5 and 4 m, its lamp 0.85 m from the camera, the
    calibration patch and marker on a bracket in view), API on 127.0.0.1:8080."""
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 30.0}),
        lamp=DeviceConfig(driver="sim"),
        rangefinder=DeviceConfig(driver="sim-ping1d"),
        simulation={"scene": "survey", "size": [1280, 720], "water": "jerlov-IA", "lamp_offset": [0.3, -0.8, 0.0],
                    "speed": 0.4, "altitude": [1.5, 4.0], "altitude_period": 120.0, "seed": 0},
        # A single pixel's σ here is ~2 % of its range (measured: median 2.1 %), a speckled picture
        # at 2-98 % colour limits; 3×3 mean smoothing of the range map brings it to 0.7 %.
        processing=ProcessingConfig(smoothing="mean"),
    )


TANK_RAIL_M = (0.5, 4.0)
"""Where the simulated tank's rail can put the plate (m from the camera along the optical axis)."""


def tank_config() -> DaemonConfig:
    """``uwcam run --simulate tank``: the embedded simulated tank. The camera faces the marker
    calibration plate (charuco-plate) on a rail 1 m away, square to the optical axis, in the default
    vehicle's water with its lamp where the default vehicle has it; no vehicle bracket in view. The
    exposure is set on the plate at 1 m and then held, as for a calibration; the image is 640×360
    (the vehicle's field of view at half its resolution) so that moving the plate re-renders the
    view in seconds. Move the plate with ``PUT /api/v1/simulation/plate``."""
    return DaemonConfig(
        camera=CameraConfig(driver="sim", options={"fps": 15.0}),
        lamp=DeviceConfig(driver="sim"),
        rangefinder=DeviceConfig(driver="sim-ping1d"),
        simulation={"scene": "plate", "plate_rig": "charuco-plate", "distance": 1.0, "size": [640, 360],
                    "water": "jerlov-IA", "lamp_offset": [0.3, -0.8, 0.0], "seed": 0},
    )


SIMULATED_SETUPS = {"vehicle": default_config, "tank": tank_config}
"""What ``uwcam run --simulate NAME`` starts."""
