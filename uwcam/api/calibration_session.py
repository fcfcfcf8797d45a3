"""/api/v1/calibration/session: a guided tank calibration (start, live feedback, captures, fit with
plots and report, held-back validation, accept or cancel). The session's logic is in
:mod:`uwcam.calibration.session`; here only HTTP. Every handler is sync (threadpool): marker
detection, waiting for frames, fitting and writing captures never run on the event loop.

The session is kept on disk (:mod:`uwcam.calibration.session_store`) in
``<state_dir>/calibration-session`` (or ``$XDG_STATE_HOME/uwcam/calibration-session``, default
``~/.local/state/uwcam/…``, when no state folder is configured) from its start until it is
accepted or cancelled; a daemon that restarts resumes it at the first request.
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
import time
from collections.abc import Iterator
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from uwcam.api.common import get_daemon, latest
from uwcam.api.profiles import NAME as PROFILE_NAME
from uwcam.calibration.session import CalibrationSession, SessionError
from uwcam.calibration.session_store import load_session, remove_session, save_session
from uwcam.config import Flag, Real, Whole  # numbers are numbers: "1" and true are refused, as docs/api.md says
from uwcam.runtime.daemon import Daemon
from uwcam.fileio import UserInputError
from uwcam.optics.geometry import Intrinsics

router = APIRouter(prefix="/api/v1/calibration/session", tags=["calibration"])
# Guards starting, replacing and ending the one session of an app.
_LOCK = threading.Lock()
# A rangefinder reading older than this is not compared with the typed distance (s).
RANGEFINDER_MAX_AGE_S = 1.0


class Start(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rig: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,64}$")] = "charuco-plate"
    """A rig shipped in calibration_rigs/, with markers."""
    intrinsics: tuple[Annotated[Real, Field(ge=1, le=1e5)], Annotated[Real, Field(ge=1, le=1e5)],
                      Annotated[Real, Field(ge=-1e5, le=1e5)], Annotated[Real, Field(ge=-1e5, le=1e5)]] | None = None
    """fx, fy, cx, cy in pixels; default: the active profile's."""
    frames_per_capture: Annotated[Whole, Field(ge=1, le=50)] = 4
    distance_tolerance_m: Annotated[Real, Field(gt=0, le=1)] = 0.05
    """How far a typed distance may differ from the markers' and the rangefinder's (at least 2 % of it)."""


class CaptureRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    distance_m: Annotated[Real, Field(ge=0.05, le=100)]
    """Camera-to-plate distance along the optical axis, as measured (m)."""
    frames: Annotated[Whole, Field(ge=1, le=50)] | None = None
    """Frames to take (default: the session's frames_per_capture)."""
    held_back: Flag = False
    """Keep this distance out of the fit, to validate the new profile."""


class Accept(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: Annotated[str, Field(pattern=f"^{PROFILE_NAME.pattern}$")]
    """Name the new profile is saved and activated under: the profiles route's rule (letters, digits,
    '.', '_' and '-', 1–64, not starting with '.': such a file is hidden and skipped at the next start)."""


def session_folder(d: Daemon) -> str:
    """Where the open session is kept until accepted or cancelled."""
    root = d.state_dir or os.path.join(os.environ.get("XDG_STATE_HOME") or os.path.expanduser("~/.local/state"), "uwcam")
    return os.path.join(root, "calibration-session")


def _folder(request: Request) -> str:
    """This daemon's session folder, fixed at its first use (the environment may change after)."""
    state = request.app.state
    if getattr(state, "calibration_session_folder", None) is None:
        state.calibration_session_folder = session_folder(state.daemon)
    return state.calibration_session_folder


def _current(request: Request) -> CalibrationSession | None:
    """The open session, resumed from disk on the first request after the daemon started."""
    state = request.app.state
    with _LOCK:
        if not getattr(state, "calibration_session_resumed", False):
            state.calibration_session_resumed = True
            if getattr(state, "calibration_session", None) is None:
                published = state.daemon.pipeline.latest if state.daemon.pipeline else None
                shape = None if published is None else published.frame.data.shape
                state.calibration_session = load_session(_folder(request), shape)
        return getattr(state, "calibration_session", None)


def open_session(request: Request) -> dict | None:
    """The open session in brief (for the status), None when there is none."""
    session = _current(request)
    if session is None:
        return None
    return {"id": session.id, "state": session.state, "captures": len(session.captures)}


def _session(request: Request) -> CalibrationSession:
    session = _current(request)
    if session is None:
        raise HTTPException(status_code=404, detail="no calibration session; POST /api/v1/calibration/session to start one")
    return session


def _not_the_plate(d: Daemon, dictionary: str) -> tuple[tuple[int, ...], tuple[tuple[int, int, int, int], ...]]:
    """Marker ids and image regions that belong to the vehicle, never to the plate: the patch's marker
    (configured, or the simulated vehicle's) when it shares the plate's dictionary, and the vehicle mask."""
    ids = []
    patch = d.pipeline.processing.patch if d.pipeline else None
    if patch is not None and patch.marker is not None and patch.marker.dictionary == dictionary:
        ids.append(int(patch.marker.id))
    if d.rig is not None and d.rig.scene != "plate":
        from uwcam.runtime.simulated_rig import PATCH_SCENES

        if d.rig.scene in PATCH_SCENES:
            from uwcam.simulation.scene import MARKER_ID

            ids.append(MARKER_ID)  # the simulated vehicle's patch marker, DICT_4X4_50
    mask = d.pipeline.processing.vehicle_mask if d.pipeline else []
    return tuple(sorted(set(ids))), tuple(tuple(int(v) for v in b) for b in mask)


def _refuse(exc: SessionError) -> HTTPException:
    return HTTPException(status_code=exc.status, detail=str(exc))


@contextlib.contextmanager
def _refusing(session: CalibrationSession) -> Iterator[None]:
    """The session's lock held; a SessionError inside becomes the HTTP refusal with its reason."""
    with session.lock:
        try:
            yield
        except SessionError as exc:
            raise _refuse(exc) from None


def _rangefinder(d: Daemon) -> float | None:
    rf = d.rangefinder
    if rf is None or rf.health.state.value != "ok":
        return None
    reading = rf.latest()
    if reading is None or reading.age_s > RANGEFINDER_MAX_AGE_S:
        return None
    return float(reading.range_m)


def _exposure_lock(d: Daemon) -> dict:
    """Whether the exposure stays fixed for the session, and how we know."""
    cam = d.camera
    settings = cam.settings if cam else None
    unsupported = [] if cam is None or cam.report is None else list(cam.report.unsupported)
    frame = d.pipeline.latest.frame if d.pipeline and d.pipeline.latest else None
    exposure = None if frame is None else frame.exposure_us
    if settings is not None and settings.exposure_us is not None and "exposure_us" not in unsupported:
        return {"locked": True, "how": f"fixed at {settings.exposure_us:g} µs by the camera settings", "exposure_us": exposure}
    if exposure is not None:
        return {"locked": False, "how": "the camera reports its exposure: every capture is checked against the first",
                "exposure_us": exposure}
    return {"locked": False, "exposure_us": None,
            "how": "the camera neither takes a fixed exposure setting nor reports its exposure; keep it on manual"}


@router.post("", status_code=201)
def start(body: Start, request: Request, d: Daemon = Depends(get_daemon)) -> dict:
    """Start a session (one at a time). The active profile gives channels, dark level, noise floor
    and lamp position; the exposure is locked where the camera allows."""
    from uwcam.calibration.rig import builtin_rig_path, load_rig

    try:
        rig = load_rig(builtin_rig_path(body.rig))
    except UserInputError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
    base = d.profiles[d.profile_name]
    if body.intrinsics is not None:
        intr = Intrinsics(*body.intrinsics)
    elif base.camera_intrinsics() is not None:
        intr = base.camera_intrinsics()
    else:
        raise HTTPException(status_code=422, detail="the active profile has no intrinsics; give intrinsics [fx, fy, cx, cy]")
    ignore_ids, ignore_regions = _not_the_plate(d, rig.plate.markers.dictionary if rig.plate.markers else "")
    _current(request)  # a session kept on disk by an earlier run counts as running
    with _LOCK:
        current = getattr(request.app.state, "calibration_session", None)
        if current is not None and current.state in ("positioning", "fitted"):
            raise HTTPException(status_code=409, detail=f"session {current.id} is running; cancel it first "
                                                        "(DELETE /api/v1/calibration/session)")
        try:
            session = CalibrationSession(body.rig, rig, intr, base, body.frames_per_capture, body.distance_tolerance_m,
                                         _exposure_lock(d), ignore_ids=ignore_ids, ignore_regions=ignore_regions)
        except SessionError as exc:
            raise _refuse(exc) from None
        folder = _folder(request)
        remove_session(folder)  # a finished session's leftovers, if any
        try:
            save_session(session, folder)
        except OSError as exc:
            raise HTTPException(status_code=507, detail=f"cannot keep the session in {folder}: {exc.strerror or exc}; "
                                                        "free some space or set state_dir") from None
        request.app.state.calibration_session = session
    return session.summary()


@router.get("")
def status(request: Request, distance: Annotated[float | None, Query(ge=0.05, le=100, allow_inf_nan=False)] = None,
           held_back: bool = False, d: Daemon = Depends(get_daemon)) -> dict:
    """The session and live feedback from the newest frame; ``distance``: the distance typed so far (m);
    ``held_back``: whether the next capture would be held back. ``live.capture_ok`` says whether a
    capture now would be accepted, ``live.refusals`` why not (the capture's own checks)."""
    session = _session(request)
    published = latest(d)
    frame = published.frame
    live = session.feedback(frame.data, distance, _rangefinder(d), frame.exposure_us, held_back, frame.exposures()[0])
    with session.lock:
        return {"session": session.summary(), "live": live}


@router.delete("")
def cancel(request: Request) -> dict:
    """End the session; nothing it measured is kept and no profile changes."""
    session = _session(request)
    with _LOCK:
        session.state = "cancelled"
        request.app.state.calibration_session = None
        remove_session(_folder(request))
    return {"id": session.id, "state": "cancelled"}


def _take_frames(d: Daemon, count: int, timeout_s: float) -> list:
    """The next ``count`` frames the loop publishes after now (their raw data, never modified after publication)."""
    t0 = time.monotonic_ns()
    box: queue.Queue = queue.Queue(maxsize=count)

    def hand_off(published) -> None:  # in the loop's thread: only hand off
        if published.frame.host_monotonic_ns > t0:
            try:
                box.put_nowait(published.frame)
            except queue.Full:
                pass

    d.pipeline.subscribe(hand_off)
    frames = []
    try:
        deadline = time.monotonic() + timeout_s
        while len(frames) < count:
            try:
                frames.append(box.get(timeout=max(deadline - time.monotonic(), 0.001)))
            except queue.Empty:
                raise HTTPException(status_code=503, detail=f"only {len(frames)} of {count} frames arrived in {timeout_s:g} s; "
                                                            "see /api/v1/status") from None
    finally:
        d.pipeline.unsubscribe(hand_off)
    return frames


@router.post("/captures", status_code=201)
def capture(body: CaptureRequest, request: Request, d: Daemon = Depends(get_daemon)) -> dict:
    """Take N frames with the plate at ``distance_m``. Refused with the reason, keeping nothing, when the
    plate is not found, saturated, too dark, or not where the markers or the rangefinder say."""
    session = _session(request)
    count = body.frames or session.frames_per_capture
    frames = _take_frames(d, count, timeout_s=5.0 + 2.0 * count)
    with _refusing(session):
        cap = session.capture([f.data for f in frames], body.distance_m, body.held_back, _rangefinder(d),
                              [f.exposure_us for f in frames], [f.exposures()[0] for f in frames])
        try:
            save_session(session, _folder(request))
        except OSError as exc:  # kept in memory: the session goes on, but would not survive a restart
            session.captures.remove(cap)
            raise HTTPException(status_code=507, detail=f"cannot keep the capture on disk ({exc.strerror or exc}); "
                                                        "free some space and capture again") from None
        return {"capture": cap.summary(), "session": session.summary()}


@router.post("/fit")
def fit(request: Request) -> dict:
    """Fit the captures not held back; validate on the held-back ones. JSON with residuals; plots under plots/."""
    session = _session(request)
    with _refusing(session):
        return session.fit()


@router.get("/plots/{name}.png", responses={200: {"content": {"image/png": {}}}})
def plot(name: str, request: Request) -> Response:
    """One of the fit's plots (PNG): fits, residuals, noise model, plate overlay."""
    session = _session(request)
    with _refusing(session):
        return Response(session.plot(name), media_type="image/png")


@router.get("/report.html", response_class=HTMLResponse)
def report(request: Request) -> HTMLResponse:
    """The fit as one self-contained HTML page (tables and every plot), to download and keep."""
    session = _session(request)
    with _refusing(session):
        page = session.report()
    return HTMLResponse(page, headers={"Content-Disposition": f'attachment; filename="tank-calibration-{session.id}.html"'})


@router.post("/accept")
def accept(body: Accept, request: Request, d: Daemon = Depends(get_daemon)) -> dict:
    """Save the validated profile under ``name`` and make it active; the session ends."""
    session = _session(request)
    with _refusing(session):
        profile = session.acceptable()
        active = d.profiles[d.profile_name]
        if len(profile.channels) != len(active.channels):
            raise HTTPException(status_code=409, detail="the new profile's channels do not match the camera's")
        profile = profile.model_copy(update={"name": body.name})
        d.save_profile(body.name, profile)
        d.activate(body.name)
        session.state = "accepted"
    with _LOCK:
        request.app.state.calibration_session = None
        remove_session(_folder(request))
    return {"name": body.name, "active": True, "session": session.id,
            "attenuation_differences": dict(zip(profile.channel_names, map(float, profile.array("attenuation_difference"))))}


__all__ = ["router"]
