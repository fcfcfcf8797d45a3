"""docs/api.md lists every route the application serves: its table is made from the app itself
(uwcam/api/route_table.py) and compared here, so a new or changed route cannot go undocumented."""

from pathlib import Path

import pytest

from uwcam.api.route_table import BEGIN, END, default_app, rewrite, route_table

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def test_docs_api_md_lists_every_route_as_the_app_serves_it():
    text = DOC.read_text(encoding="utf-8")
    assert rewrite(text, route_table(default_app())) == text, \
        "docs/api.md's route table differs from the app's routes: run `python -m uwcam.api.route_table docs/api.md`"


def test_the_table_has_every_openapi_path_and_the_websocket_routes():
    app = default_app()
    table = route_table(app)
    # Counted from the schema itself, independently of how the table is written.
    operations = [(m.upper(), p) for p, ops in app.openapi()["paths"].items() for m in ops]
    for method, path in operations:
        assert f"`{method} {path}`" in table
    for path in ("/api/v1/stream", "/api/v1/view"):
        assert f"`WS {path}`" in table
    # Routes the last round left undocumented are there.
    for path in ("/api/v1/recordings", "/api/v1/calibration/session", "/api/v1/snapshot/normals", "/register_service"):
        assert f" {path}`" in table


def test_rewrite_refuses_a_document_without_the_markers():
    with pytest.raises(ValueError, match="no generated route table"):
        rewrite("# no table here", "| a | b |")
    assert rewrite(f"x\n{BEGIN}\nold\n{END}\ny", "new") == f"x\n{BEGIN}\nnew\n{END}\ny"
