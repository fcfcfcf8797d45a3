"""``uwcam reprocess``: range recorded dives again from their raw frames, in one process or on a
Dask cluster.

Every ranged frame in a recording carries what it was ranged with (``/uwcam/ranging``: the
attenuation differences tracked live from the patch, the log constants from the rangefinder,
whether ambient light was subtracted, the processing settings), so a frame can be ranged again
on its own. That makes the work embarrassingly parallel: a recording is cut into parts at its
MCAP chunk boundaries (time ranges from the chunk index), and each part is read and ranged by
whoever runs it; only the results travel back to be written in order.

With the recorded calibration the result is the recorded depth, bit for bit. With another
profile (``--profile``), the live corrections recorded are carried over as corrections
relative to the calibration: the tracked drift of the attenuation differences (a change of
water) and the surface's log constants relative to the target's (a surface of another hue).
"""

from __future__ import annotations

import logging
import os
import tempfile
from functools import partial
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from uwcam.recording import format as rec
from uwcam.recording.chunk_check import CorruptChunk, find_corrupt_chunks
from uwcam.extras import require_extra
from uwcam.fileio import UserInputError
from uwcam.recording.records import to_depth
from uwcam.calibration.profile import CalibrationProfile, load_profile, profile_to_yaml
from uwcam.ranging.estimator import DEFAULT_SMOOTHING_TARGET, RangeEstimator, range_frame

END_OF_TIME = 2**63 - 1
DECIMATED = object()
"""Marks a frame whose raw image the recorder left out to fit its disk budget (not a loss)."""
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Part:
    """Messages of one recording with log times in [start_ns, end_ns): one unit of work."""

    path: str
    start_ns: int
    end_ns: int
    skip_offsets: tuple[int, ...] = ()
    """Byte offsets of chunks that failed their CRC check: never read."""


@dataclass
class FrameResult:
    """One frame ranged again, its messages already encoded (on the worker, not the client)."""

    log_time_ns: int
    width: int
    height: int
    depth: bytes
    """foxglove.RawImage 32FC1, metres along the optical axis."""
    variance: bytes
    """foxglove.RawImage 32FC1, m²."""
    reasons: bytes
    """foxglove.RawImage mono8."""
    ranging: dict


@dataclass
class PartResult:
    part: Part
    frames: list[FrameResult] = field(default_factory=list)
    profiles: dict[str, str] = field(default_factory=dict)
    """Profiles used, by name, as YAML (attached to the output)."""
    skipped: list[tuple[int, str]] = field(default_factory=list)
    """Ranged frames not ranged again: (log time ns, why)."""


def _open(path: str):
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise UserInputError(f"cannot read {path}: {exc.strerror}") from None
    return fh


def _summary(path: str):
    """The MCAP summary (None for a file without one); UserInputError if it is no MCAP file, or
    one its writer never finished (saying how to repair it)."""
    from mcap.exceptions import McapError

    if not rec.is_complete(path):
        with _open(path) as fh:
            is_mcap = fh.read(8) == b"\x89MCAP0\r\n"
        if is_mcap:
            raise UserInputError(f"{path} was never finished (its recorder was stopped before closing it, e.g. killed "
                                 f"or out of disk space); repair it with `uwcam repair {path}`, then reprocess it")
    with _open(path) as fh:
        try:
            return rec.open_reader(fh).get_summary()
        except (McapError, ValueError, EOFError) as exc:
            raise UserInputError(f"{path} is not a readable MCAP recording ({exc})") from None


def ranged_frame_count(path: str) -> int:
    """Frames with a range whose raw image was kept, in a recording (from its statistics; 0 if it
    has none): at most its ranging records and at most its raw images (frames decimated to fit the
    disk budget have a ranging record and no image; frames not ranged have an image and no record)."""
    summary = _summary(path)
    if summary is None or summary.statistics is None:
        return 0
    counts = summary.statistics.channel_message_counts

    def count(topic: str) -> int:
        return sum(counts.get(cid, 0) for cid, ch in summary.channels.items() if ch.topic == topic)

    return min(count(rec.RANGING), count(rec.IMAGE))


def plan(path: str, part_mb: float = 64.0, skip_offsets: tuple[int, ...] = ()) -> list[Part]:
    """Cut a recording into parts of about ``part_mb`` megabytes of (uncompressed) chunks each,
    at chunk boundaries, by the chunks' start times: big enough that opening the file and
    building the estimator are small beside the ranging, small enough to spread a dive over
    many workers. A file without a chunk index (a repaired one) is a single part."""
    summary = _summary(path)
    if summary is None or not summary.chunk_indexes:
        return [Part(path, 0, END_OF_TIME, skip_offsets)]
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.message_start_time)
    bounds, size = [0], 0
    for chunk in chunks:
        if size >= part_mb * 1e6 and chunk.message_start_time > bounds[-1]:
            bounds.append(chunk.message_start_time)
            size = 0
        size += chunk.uncompressed_size
    return [Part(path, a, b, skip_offsets) for a, b in zip(bounds, bounds[1:] + [END_OF_TIME])]


def _corrected(profile: CalibrationProfile, recorded: CalibrationProfile | None, record: dict) -> tuple[NDArray, NDArray]:
    v = np.array(record["attenuation_differences"], dtype=np.float64)
    b = np.array(record["log_constants"], dtype=np.float64)
    if recorded is None or profile is recorded:
        return v, b
    return (profile.array("attenuation_difference") + (v - recorded.array("attenuation_difference")),
            profile.array("log_constant") + (b - recorded.array("log_constant")))


def _water_and_compensation(cache: dict, profile: CalibrationProfile, estimator: RangeEstimator, key: tuple,
                            shape: tuple[int, ...], record: dict, open_water: NDArray | None,
                            ambient: NDArray | None) -> tuple:
    """(transform, open-water light, light scale) for :func:`range_frame`, as the frame loop had them
    for this frame (its record says whether backscatter was compensated and what the water's light
    came from); built once per profile, settings and open-water frame (``cache``)."""
    from uwcam.water.backscatter import MAX_FRAMES_AVERAGED, frames_averaged_count
    from uwcam.water.frame_compensator import BackscatterCompensator, compensation, compensation_iterations

    source = record.get("water")  # recordings made before the water's light was judged have none
    if source is None:
        return None, None, None
    # As the loop: compensated wherever the profile knows the water's light, asked for or not.
    iterations = compensation_iterations(record["processing"].get("backscatter"), profile)
    water_frame = open_water if source == "open-water frame" else None
    if water_frame is None and source == "open-water frame":
        raise UserInputError(f"frame {record['number']} was judged against an open-water frame that the recording "
                             "does not hold; it cannot be ranged again the same way")
    # How many frames the open-water frame is the mean of (recordings before it was written: 1).
    recorded = record.get("open_water_frames")
    water_frames = frames_averaged_count(1 if recorded is None else recorded)
    if water_frames is None:
        raise UserInputError(f"frame {record['number']}'s record gives {recorded!r} as the open-water frame's count of "
                             f"frames, not a count from 1 to {MAX_FRAMES_AVERAGED}; the recording is damaged")
    made_for = (*key, iterations, tuple(shape), source, water_frames)
    if made_for not in cache:
        comp = BackscatterCompensator(profile, tuple(shape[:2]), iterations, water_frame, pair=key[1],
                                      path_length_bounds=key[2], open_water_frames=water_frames)
        cache[made_for] = (comp, comp.water)
    comp, water = cache[made_for]
    scale = None if record.get("light_scale") is None else np.asarray(record["light_scale"], dtype=np.float64)
    transform = compensation(comp, estimator, ambient, scale)
    return transform, water, scale


def process_part(part: Part, profile_yaml: str | None = None, kernel_threads: int | None = None) -> PartResult:
    """Range every ranged frame of one part again. ``profile_yaml``: a profile to use instead of
    the one each frame was recorded with. ``kernel_threads``: threads of the compiled ranging
    kernel (None: numba's default, all cores). Runs on a Dask worker or in this process."""
    import yaml

    if kernel_threads is not None:
        import numba

        numba.set_num_threads(kernel_threads)  # a per-thread setting: this worker thread only

    from uwcam.calibration.profile import profile_from_mapping

    override = None if profile_yaml is None else profile_from_mapping(yaml.safe_load(profile_yaml), "--profile")
    out = PartResult(part)
    estimators: dict[tuple, RangeEstimator] = {}
    factors: dict[tuple, NDArray] = {}
    with _open(part.path) as fh:
        reader = rec.open_checked_reader(fh, part.skip_offsets)
        recorded = rec.read_profiles(reader)
        ambient = None
        open_water = None
        if part.start_ns > 0:  # the ambient estimate and open-water frame in force when the part begins
            for _s, _c, _m, decoded in reader.iter_decoded_messages(topics=[rec.AMBIENT], ending_before=part.start_ns,
                                                                    reverse=True):
                ambient = rec.decode_raw_image(decoded).astype(np.float64)
                break
            for _s, _c, _m, decoded in reader.iter_decoded_messages(topics=[rec.OPEN_WATER], ending_before=part.start_ns,
                                                                    reverse=True):
                open_water = rec.decode_raw_image(decoded).astype(np.float32)
                break
        lit: dict[tuple, tuple] = {}
        images: dict[int, NDArray] = {}
        exposures: dict[int, tuple] = {}
        for _s, channel, message, decoded in reader.iter_decoded_messages(
                topics=[rec.IMAGE, rec.IMAGE_METADATA, rec.AMBIENT, rec.OPEN_WATER, rec.RANGING], starting_at=part.start_ns,
                ending_before=part.end_ns):
            t = message.log_time
            if channel.topic == rec.IMAGE:
                images[t] = rec.decode_raw_image(decoded)
                continue
            if channel.topic == rec.IMAGE_METADATA:
                exposures[t] = (DECIMATED if not decoded.get("raw_kept", True)  # no image, by design
                                else (decoded.get("exposure_us"), decoded.get("gain_db")))  # per channel, or None
                continue
            if channel.topic == rec.AMBIENT:
                ambient = rec.decode_raw_image(decoded).astype(np.float64)
                continue
            if channel.topic == rec.OPEN_WATER:
                open_water = rec.decode_raw_image(decoded).astype(np.float32)
                lit.clear()  # built for the frame before
                continue
            record, raw = decoded, images.pop(t, None)
            if raw is None:
                if exposures.pop(t, None) is DECIMATED:
                    continue  # its image was left out to fit the disk budget, as the recording says
                # its image was lost (a write cut short, a damaged chunk): nothing to range
                out.skipped.append((t, f"frame {record.get('number', '?')}: its raw image is missing"))
                continue
            was = recorded.get(record["profile"])
            profile = override or was
            if profile is None:
                raise UserInputError(f"{part.path}: frame {record['number']} was ranged with profile "
                                     f"'{record['profile']}', which is not attached; give --profile")
            if raw.ndim != 3 or raw.shape[-1] != len(profile.channels):
                raise UserInputError(f"{part.path} has {raw.shape[-1] if raw.ndim == 3 else 1}-channel frames but profile "
                                     f"'{profile.name}' has {len(profile.channels)} channels")
            proc = record["processing"]
            key = (profile.name, tuple(proc["pair"]) if proc["pair"] else None, tuple(proc["path_length_bounds"]))
            if key not in estimators:
                estimators[key] = RangeEstimator(profile, pair=key[1], path_length_bounds=key[2])
            est = estimators[key]
            v, b = _corrected(profile, was, record)
            est.set_attenuation_differences(v)
            est.set_log_constants(b)
            exposure, gain = exposures.pop(t, (None, None))
            est.set_exposure(exposure, gain)  # each channel's exposure when it was taken: exact whatever it was
            frame_ambient = ambient if record["ambient_subtracted"] else None
            transform, water, scale = _water_and_compensation(lit, profile, est, key, raw.shape, record, open_water,
                                                              frame_ambient)
            # Recordings made before the vehicle mask existed have none.
            result = range_frame(est, raw, proc["smoothing"], proc["smoothing_stage"], frame_ambient,
                                 proc.get("vehicle_mask") or (), transform, water, scale, None,
                                 proc.get("smoothing_target", DEFAULT_SMOOTHING_TARGET))
            shape = (profile.name, *raw.shape[:2])
            if shape not in factors:
                factors[shape] = rec.depth_factor(profile, *raw.shape[:2])
            depth, variance = to_depth(result.range, result.variance, factors[shape])
            ranging = dict(record, profile=profile.name, attenuation_differences=[float(x) for x in v],
                           log_constants=[float(x) for x in b], reprocessed_from=record["profile"])
            h, w = raw.shape[:2]
            out.frames.append(FrameResult(t, w, h, rec.raw_image(depth, t, "32FC1"), rec.raw_image(variance, t, "32FC1"),
                                          rec.raw_image(result.reasons, t, "mono8"), ranging))
            if profile.name not in out.profiles:
                out.profiles[profile.name] = profile_to_yaml(profile)
    return out


def _in_order(parts: list[Part], fn: Callable[[Part], PartResult], scheduler: str | None, workers: int | None,
              ) -> Iterator[PartResult]:
    """Results of ``fn`` over the parts, in order: here, or on a Dask cluster (``"local"``: a
    cluster of ``workers`` processes on this machine started for the run; otherwise the
    address of a running scheduler, whose workers must see the same file paths)."""
    if scheduler is None:
        for part in parts:
            yield fn(part)
        return
    distributed = require_extra("cluster")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster

    # On a cluster the parallelism is across parts: one kernel thread per task, or every worker's
    # numba threads would fight over the same cores.
    fn = partial(fn, kernel_threads=1)
    cluster = None
    if scheduler == "local":
        n = workers or max(1, min(len(parts), os.cpu_count() or 1))
        # Processes, one thread each (decoding and encoding hold the GIL); idle OpenMP threads
        # sleep rather than spin.
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               env={"OMP_WAIT_POLICY": "PASSIVE"})
        client = Client(cluster)
    else:
        try:
            client = Client(scheduler, timeout="15s")
        except (OSError, TimeoutError) as exc:
            raise UserInputError(f"cannot reach the Dask scheduler at {scheduler} ({exc}); is it running?") from None
    try:
        window = 2 * max(1, len(client.scheduler_info(n_workers=-1)["workers"]))
        futures = []
        # A bounded window of parts in flight keeps the client's memory to a few parts' results.
        for i, part in enumerate(parts):
            futures.append(client.submit(fn, part, pure=False))
            if len(futures) > window:
                yield futures.pop(0).result()
        for f in futures:
            yield f.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def output_paths(inputs: list[str], output: str) -> list[str]:
    """One output per input: ``output`` itself for one input and an .mcap name, else a folder."""
    if len(inputs) == 1 and output.endswith(".mcap"):
        paths = [output]
    else:
        os.makedirs(output, exist_ok=True)
        paths = [os.path.join(output, os.path.basename(p)) for p in inputs]
        if len(set(paths)) != len(paths):
            raise UserInputError("two inputs share a file name; reprocess them into separate folders")
    for p in paths:
        if os.path.exists(p):
            raise UserInputError(f"{p} exists; choose another output (outputs are never overwritten)")
    return paths


def corrupt_chunks(path: str) -> list[CorruptChunk]:
    """The chunks of a recording that fail their CRC check or cannot be read."""
    _summary(path)  # a readable, finished MCAP file, or the reason why not
    with _open(path) as fh:
        return find_corrupt_chunks(fh, rec.RANGING)


def describe_corrupt(path: str, bad: list[CorruptChunk]) -> str:
    """One line: how many chunks are damaged, which ranged frames they held, the first reason."""
    summary = _summary(path)
    total = len(summary.chunk_indexes) if summary is not None and summary.chunk_indexes else None
    known = [t for c in bad if c.frames_ns is not None for t in c.frames_ns]
    frames = f"{len(known)} ranged frame(s) (log times {_times(known)})" if known else "the frames they hold"
    if any(c.frames_ns is None for c in bad):
        frames += f"; frames logged {_times([t for c in bad if c.frames_ns is None for t in (c.start_ns, c.end_ns)])}"
    return (f"{path}: {len(bad)}{f' of {total}' if total else ''} chunk(s) fail their CRC check (damaged bytes), "
            f"losing {frames}; first: {bad[0].reason}")


def _times(ns: list[int], most: int = 4) -> str:
    shown = ", ".join(f"{t / 1e9:.3f} s" for t in sorted(ns)[:most])
    return shown + (f" … ({len(ns)} in all)" if len(ns) > most else "")


def reprocess(inputs: Iterable[str], output: str, profile: str | None = None, scheduler: str | None = None,
              workers: int | None = None, progress: bool = True, part_mb: float = 64.0, skip_corrupt: bool = False,
              warn: Callable[[str], None] | None = None) -> list[str]:
    """Range recordings again into new MCAP files with depth, variance, reasons and ranging topics.
    Returns the output paths; each is written to a temporary name and renamed when complete.

    Every chunk's CRC is checked first: a recording with damaged chunks is refused
    (UserInputError, nothing written) unless ``skip_corrupt``, when its damaged chunks are left
    out. Every ranged frame not ranged again (in a damaged chunk, or its image missing) is told
    to ``warn`` (default: the log), with why."""
    from tqdm import tqdm

    warn = warn or log.warning
    inputs = list(inputs)
    for p in inputs:
        if not os.path.isfile(p):
            raise UserInputError(f"recording {p} does not exist")
    outputs = output_paths(inputs, output)
    damaged = {p: corrupt_chunks(p) for p in inputs}
    for p, bad in damaged.items():
        if bad and not skip_corrupt:
            raise UserInputError(describe_corrupt(p, bad) + "; nothing written: give --skip-corrupt to reprocess the "
                                                            "rest without them")
        if bad:
            warn("skipping damaged chunks of " + describe_corrupt(p, bad))
    profile_yaml = None
    if profile is not None:
        profile_yaml = profile_to_yaml(load_profile(profile))
    total = sum(ranged_frame_count(p) for p in inputs)
    fn = partial(process_part, profile_yaml=profile_yaml)
    class Bar(tqdm):
        monitor_interval = 0  # no monitor thread: updates come once per part anyway

    bar = Bar(total=total or None, unit="frame", desc="reprocess", disable=not progress, dynamic_ncols=True)
    results = None
    try:
        parts_by_input = [plan(p, part_mb, tuple(c.offset for c in damaged[p] if c.offset is not None)) for p in inputs]
        flat = [part for parts in parts_by_input for part in parts]
        results = _in_order(flat, fn, scheduler, workers)
        for parts, out_path in zip(parts_by_input, outputs):
            _write_output(out_path, (next(results) for _ in parts), bar, warn)
    finally:
        if results is not None:
            results.close()  # on an error too: the Dask client and any local cluster shut down now
        bar.close()
    return outputs


def _write_output(path: str, results: Iterable[PartResult], bar, warn: Callable[[str], None]) -> None:
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".reprocess-", suffix=".mcap", dir=folder)
    os.close(fd)
    out = None
    try:
        out = rec.McapFile(tmp, replace=True, compression="zstd")  # the empty temporary file made above; offline, so the smallest
        attached: set[str] = set()
        last_profile = None
        fused = 0  # frames the loop had fused over time (docs/physics.md §11)
        for result in results:
            for fr in result.frames:
                name = fr.ranging["profile"]
                if name not in attached:
                    out.attach(f"{rec.PROFILE_PREFIX}{name}.yaml", rec.PROFILE_MEDIA_TYPE,
                               result.profiles[name].encode(), fr.log_time_ns)
                    attached.add(name)
                if name != last_profile:
                    import yaml

                    from uwcam.calibration.profile import profile_from_mapping

                    prof = profile_from_mapping(yaml.safe_load(result.profiles[name]))
                    out.write(rec.CALIBRATION, "foxglove.CameraCalibration",
                              rec.camera_calibration(prof, fr.width, fr.height, fr.log_time_ns), fr.log_time_ns)
                    last_profile = name
                t = fr.log_time_ns
                fused += bool(fr.ranging.get("processing", {}).get("temporal"))
                out.write_json(rec.RANGING, fr.ranging, t)
                out.write(rec.DEPTH, "foxglove.RawImage", fr.depth, t)
                out.write(rec.VARIANCE, "foxglove.RawImage", fr.variance, t)
                out.write(rec.REASONS, "foxglove.RawImage", fr.reasons, t)
            bar.update(len(result.frames))
            for t, why in result.skipped:
                warn(f"{result.part.path}: skipped the ranged frame logged at {t / 1e9:.3f} s ({why})")
        if fused:
            warn(f"{path}: {fused} frames were fused over time in the frame loop (processing.temporal); they are "
                 "ranged again each on its own, as single frames")
        out.finish()
        os.replace(tmp, path)
    except BaseException:
        if out is not None:
            out.abandon()
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
