"""A real nginx configured with BlueOS's extension route, for tests of uwcam behind BlueOS.

The route is BlueOS's own (bluerobotics/BlueOS core/services/helper/main.py, ``setup_nginx_route``:
``location /extensionv2/<name>/``, ``proxy_pass http://127.0.0.1:<port>/``, ``Host $host``,
X-Forwarded-For and -Proto, WebSocket upgrade). BlueOS serves on port 80, the Origin's default
port; these tests' nginx listens on a free port and says so in ``X-Forwarded-Port``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

from tests.waiting import wait_for
from tests.ports import free_port


@contextmanager
def blueos_nginx(folder: Path, upstream_port: int, name: str = "uwcam", pages: dict[str, str] | None = None) -> Iterator[str]:
    """Serves uwcam (on ``upstream_port``) at ``/extensionv2/<name>/`` and ``pages`` (file name →
    HTML) at the root; yields the proxy's URL, ``http://127.0.0.1:<port>``."""
    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    assert Path(nginx).exists(), "nginx is needed for the reverse-proxy tests: .ci/run installs nginx-light"
    port = free_port()
    www = folder / "www"
    www.mkdir(exist_ok=True)
    (www / "alive.html").write_text("<!doctype html><title>alive</title>")
    for file, html in (pages or {}).items():
        (www / file).write_text(html)
    conf = folder / "nginx.conf"
    # As root, nginx's workers would drop to "nobody", who cannot read pytest's private tmp folder.
    user = "user root root;" if os.geteuid() == 0 else ""
    conf.write_text(f"""
{user}
worker_processes 1;
daemon off;
pid {folder}/nginx.pid;
error_log {folder}/error.log warn;
events {{}}
http {{
  access_log off;
  client_body_temp_path {folder}/body; proxy_temp_path {folder}/proxy;
  fastcgi_temp_path {folder}/fastcgi; uwsgi_temp_path {folder}/uwsgi; scgi_temp_path {folder}/scgi;
  map $http_upgrade $connection_upgrade {{ default upgrade; '' close; }}
  server {{
    listen 127.0.0.1:{port};
    location ~ ^/[a-z0-9_-]+\\.html$ {{ root {www}; }}
    location /extensionv2/{name}/ {{
      proxy_pass http://127.0.0.1:{upstream_port}/;
      proxy_set_header Host $host;
      proxy_set_header X-Real-IP $remote_addr;
      proxy_set_header X-Forwarded-For $proxy_add_x_forwarded_for;
      proxy_set_header X-Forwarded-Proto $scheme;
      proxy_set_header X-Forwarded-Port $server_port;
      proxy_http_version 1.1;
      proxy_set_header Upgrade $http_upgrade;
      proxy_set_header Connection $connection_upgrade;
    }}
  }}
}}
""")
    proc = subprocess.Popen([nginx, "-p", str(folder), "-c", str(conf)], stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    try:
        assert wait_for(lambda: _answers(url + "/alive.html"), 10.0), "nginx did not start"
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        proc.stderr.close()


def _answers(url: str) -> bool:
    try:
        return httpx.get(url, timeout=1.0).status_code == 200
    except httpx.HTTPError:
        return False
