"""``uwcam run``, ``uwcam warmup`` and ``uwcam config check``: the daemon."""

from __future__ import annotations

import argparse

from uwcam import __version__
from uwcam.fileio import UserInputError


def require_websocket_support() -> None:
    """uvicorn serves WebSockets only with a WebSocket library beside it; without one it logs a
    warning and answers every WebSocket route with 404, so the page would have no live view."""
    import importlib

    for name in ("websockets", "wsproto"):  # what uvicorn tries, in its order
        try:
            importlib.import_module(name)
            return
        except ImportError:
            continue
    raise UserInputError("the Python package 'websockets' is missing (the page's live view and /api/v1/stream "
                         "need it): install it with '.venv/bin/pip install websockets', or run deploy/install.sh again")


def _orderly_server_class() -> type:
    import contextlib
    import signal
    import threading

    import uvicorn

    class OrderlyServer(uvicorn.Server):
        """uvicorn's server, stopped by Ctrl-C or SIGTERM in order (the lifespan stops the loop,
        switches the lamp off, releases the devices) and then done: uvicorn would raise the signal
        again afterwards, which only adds a traceback and a failed exit status to a clean stop."""

        @contextlib.contextmanager
        def capture_signals(self):  # type: ignore[override]
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            original = {sig: signal.signal(sig, self.handle_exit) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                yield
            finally:
                for sig, handler in original.items():
                    signal.signal(sig, handler)

    return OrderlyServer


def cmd_run(args: argparse.Namespace) -> int:
    import gc
    import logging
    import os

    require_websocket_support()

    from uwcam.runtime.memory import limit_malloc_arenas

    limit_malloc_arenas()  # before any thread allocates: see uwcam/runtime/memory.py

    import socket

    import uvicorn
    from pydantic import ValidationError

    from uwcam.api import create_app
    from uwcam.config import SIMULATED_SETUPS, DaemonConfig, load_config
    from uwcam.drivers.base import DeviceLost
    from uwcam.runtime.daemon import Daemon, check_devices
    from uwcam.fileio import explain_validation_error

    if args.config and args.simulate:
        raise UserInputError("give either --config FILE or --simulate NAME, not both")
    config = load_config(args.config) if args.config else SIMULATED_SETUPS[args.simulate or "vehicle"]()
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    if overrides:
        try:  # validated like the file: --port 80808 is a one-line error
            config = DaemonConfig.model_validate({**config.model_dump(), "api": {**config.api.model_dump(), **overrides}})
        except ValidationError as exc:
            raise UserInputError(explain_validation_error(exc, "command line").replace("key 'api.", "option '--")) from None
    check_devices(config)
    from uwcam.api import required_token

    required_token(config)  # before the socket is bound: no listening beyond loopback without a token
    if args.record:
        if os.path.exists(args.record):
            raise UserInputError(f"{args.record} exists; give a new file name (recordings are never overwritten)")
        if not args.record.endswith(".mcap"):
            raise UserInputError(f"--record {args.record}: the file name must end in .mcap")
        if not os.path.isdir(os.path.dirname(os.path.abspath(args.record))):
            raise UserInputError(f"--record {args.record}: its folder does not exist; create it first")
        config.recording.start_file = args.record
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    host, port = config.api.host, config.api.port
    try:  # bound before anything starts, so a port in use is one line, not a startup traceback
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.create_server((host, port), family=family, reuse_port=False)
    except OSError as exc:
        raise UserInputError(f"cannot listen on {host}:{port}: {exc.strerror or exc}; choose another --port or --host") from None
    daemon = Daemon(config)
    daemon.warm_up_in_background = True  # numba's cache filled for every setting, once per install
    try:
        app = create_app(config, daemon)
        try:
            daemon.start()  # devices and calibration: a configuration that cannot work fails here, in one line
        except DeviceLost as exc:
            # The camera's first open (a missing /dev/video*, a stream server that is down) is made
            # here, not by its supervisor, which retries only a camera lost after the start: the start
            # ends in one line, and systemd (deploy/uwcam.service) or BlueOS start the service again.
            raise UserInputError(f"a device cannot be opened at start: {exc}; connect it (or start the camera's "
                                 "stream) and start uwcam run again") from None
        where = args.config or ("embedded simulated tank" if args.simulate == "tank" else "embedded default (simulated rig)")
        shown = f"[{host}]" if ":" in host else host  # IPv6 literal
        root = f"http://{shown}:{sock.getsockname()[1]}"
        print(f"uwcam {__version__}: {where}; operator page {root}/, API {root}/docs", flush=True)
        # uvicorn handles SIGINT/SIGTERM: the lifespan then stops the loop, switches the lamp off
        # and releases the devices.
        # No per-message deflate: zlib on every multi-megabyte range map cost a third of the CPU
        # (measured with py-spy) and float maps barely compress.
        server = _orderly_server_class()(uvicorn.Config(app, log_level="warning", ws_per_message_deflate=False))
        # Everything made so far (modules, the calibration, FastAPI's routes and models: ~125,000
        # objects) lives as long as the process: out of the cyclic collector's sight, its full
        # collections no longer stop every thread for ~50 ms (a 60 fps loop then skips frames).
        gc.freeze()
        server.run(sockets=[sock])
    finally:
        daemon.stop()
        sock.close()
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    """Run the embedded default until its first range, then range small frames every way the
    processing settings allow (:func:`uwcam.runtime.warm_up.warm_up_ranging`), then stop: numba
    compiles every kernel into its on-disk cache, so that neither the first ``uwcam run`` nor a
    later change of its settings compiles anything."""
    import logging
    import time

    from uwcam.config import default_config
    from uwcam.runtime.daemon import Daemon
    from uwcam.optics import kernels
    from uwcam.ranging.estimator import RangeEstimator
    from uwcam.runtime.background_warm_up import mark_warmed_up
    from uwcam.runtime.warm_up import warm_up_everything

    if not 1.0 <= args.timeout <= 86400.0:  # also refuses nan
        raise UserInputError(f"--timeout must be 1 to 86400 seconds, got {args.timeout}")
    if kernels.BACKEND != "numba":
        print("nothing to compile: numba is not installed here (the numpy path is used)")
        return 0
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    started = time.monotonic()
    if args.profile is not None:
        # The ranging kernels for this profile's channels only (uwcam run starts this in the background).
        from uwcam.calibration.profile import load_profile

        profile = load_profile(args.profile)
        first = None
        if args.processing is not None:
            from uwcam.config import ProcessingConfig
            from uwcam.fileio import load_yaml_mapping

            first = ProcessingConfig.model_validate(load_yaml_mapping(args.processing, "processing settings"))
        warm_up_everything(RangeEstimator(profile), first)
        mark_warmed_up(len(profile.channels))
        print(f"compiled uwcam's ranging kernels for {len(profile.channels)} channels in "
              f"{time.monotonic() - started:.0f} s (kept in numba's cache)")
        return 0
    daemon = Daemon(default_config())
    try:
        daemon.start()
        deadline = time.monotonic() + args.timeout
        while daemon.pipeline.processed < 1:
            if time.monotonic() > deadline:
                raise UserInputError(f"no range within {args.timeout:g} s; try again with a longer --timeout")
            time.sleep(0.05)
        # Every other way the settings can range a frame, so that a later change compiles nothing either.
        warm_up_everything(daemon.pipeline.estimator)
        mark_warmed_up(daemon.pipeline.estimator.n_channels)
    finally:
        daemon.stop()
    print(f"compiled uwcam's kernels in {time.monotonic() - started:.0f} s (kept in numba's cache)")
    return 0


def cmd_config_check(args: argparse.Namespace) -> int:
    from uwcam.api import required_token
    from uwcam.config import load_config
    from uwcam.runtime.daemon import check_devices

    config = load_config(args.file)
    check_devices(config)
    required_token(config)
    print(f"{args.file}: valid (camera {config.camera.driver}, API {config.api.host}:{config.api.port})")
    return 0
