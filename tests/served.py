"""The daemon's application served by a real uvicorn in a thread, on an ephemeral port."""

import threading

import httpx
import uvicorn

from tests.waiting import wait_for
from uwcam.api import create_app
from uwcam.config import DaemonConfig


class Server:
    """``with Server(config) as s:`` serves the daemon at ``s.url``; ``s.http`` is a client for it."""

    def __init__(self, config: DaemonConfig) -> None:
        self.app = create_app(config)
        self.server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=0, log_level="warning", lifespan="on",
                                                    ws_per_message_deflate=False))
        self.thread = threading.Thread(target=self.server.run, name="uvicorn-test")

    def __enter__(self) -> "Server":
        self.thread.start()
        assert wait_for(lambda: self.server.started, 60.0), "server did not start"
        self.port = self.server.servers[0].sockets[0].getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        # A settings change compiles the kernels it needs in the request (never in the frame loop):
        # on a cold numba cache (a fresh copy of the tree, before `uwcam warmup`) that takes tens of seconds.
        self.http = httpx.Client(base_url=self.url, timeout=90.0)
        return self

    def __exit__(self, *exc) -> None:
        self.http.close()
        self.server.should_exit = True
        self.thread.join(timeout=30.0)

    @property
    def daemon(self):
        return self.app.state.daemon
