"""The table of every route of the API, made from the application itself (its OpenAPI schema
and its WebSocket routes), for docs/api.md: tests/test_api_docs.py keeps the two the same.

``python -m uwcam.api.route_table docs/api.md`` rewrites the table in place.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from fastapi import FastAPI
from fastapi.routing import APIWebSocketRoute

BEGIN = "<!-- routes: made from the application by `python -m uwcam.api.route_table docs/api.md`; do not edit -->"
END = "<!-- end of routes -->"


def _first_sentence(text: str) -> str:
    text = " ".join(text.split())
    match = re.match(r"(.+?\.)(\s|$)", text)
    return (match.group(1) if match else text).replace("|", "\\|").replace("``", "`")


def route_table(app: FastAPI) -> str:
    """Markdown: one row per method and path (HTTP from the OpenAPI schema, then WebSocket
    routes), with the first sentence of the route's docstring."""
    rows = ["| route | what |", "|---|---|"]
    for path, operations in app.openapi()["paths"].items():
        for method, operation in operations.items():
            what = _first_sentence(operation.get("description") or operation.get("summary") or "")
            rows.append(f"| `{method.upper()} {path}` | {what} |")
    from uwcam.api.app import ROUTERS  # what create_app includes, without a prefix

    for route in (r for router in ROUTERS for r in router.routes):
        if isinstance(route, APIWebSocketRoute):
            rows.append(f"| `WS {route.path}` | {_first_sentence(route.endpoint.__doc__ or route.name)} |")
    return "\n".join(rows)


def rewrite(document: str, table: str) -> str:
    """``document`` with the text between :data:`BEGIN` and :data:`END` replaced by ``table``."""
    if BEGIN not in document or END not in document:
        raise ValueError(f"the document has no generated route table (between {BEGIN!r} and {END!r})")
    head, rest = document.split(BEGIN, 1)
    return f"{head}{BEGIN}\n{table}\n{END}{rest.split(END, 1)[1]}"


def default_app() -> FastAPI:
    """The application of the embedded default (its routes are every configuration's)."""
    from uwcam.api import create_app
    from uwcam.config import default_config

    return create_app(default_config())


if __name__ == "__main__":  # pragma: no cover - a developer's command
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m uwcam.api.route_table docs/api.md")
    target = Path(sys.argv[1])
    target.write_text(rewrite(target.read_text(encoding="utf-8"), route_table(default_app())), encoding="utf-8")
    print(f"rewrote the route table in {target}")
