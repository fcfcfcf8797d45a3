"""The house rules of docs/architecture.md, checked: each folder of uwcam/ says its job in the
first line of its __init__.py as the page does, a module over 500 lines says why at its top,
and the pure optics import nothing above them."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "uwcam"
PAGE = (ROOT / "docs" / "architecture.md").read_text()


def plain(text: str) -> str:
    """Markup left out: roles, backticks, the pointer to the page itself, spacing."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("`", "").replace("(docs/architecture.md)", "")
    return " ".join(text.split()).rstrip(". ")


def folders() -> list[Path]:
    return sorted(p.parent for p in PACKAGE.rglob("__init__.py")
                  if "__pycache__" not in p.parts and p.parent != PACKAGE and p.parent.name != "calibrations")


def test_every_folder_says_its_job_as_the_architecture_page_does():
    rows = {m[1]: plain(m[2]) for m in re.finditer(r"^\| `(uwcam/[\w/]+)/` \| (.+?) \|$", PAGE, re.M)}
    for folder in folders():
        name = f"{folder.relative_to(ROOT)}"
        doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text()))
        assert doc, f"{name}/__init__.py has no docstring"
        first = plain(doc.split("\n\n")[0])
        assert name in rows, f"docs/architecture.md has no row for {name}/"
        assert rows[name] == first, f"{name}: the page says '{rows[name]}', its __init__.py '{first}'"


def test_a_module_over_500_lines_says_why():
    for path in sorted(PACKAGE.rglob("*.py")):
        lines = path.read_text().count("\n")
        if lines > 500:
            doc = ast.get_docstring(ast.parse(path.read_text())) or ""
            assert "over 500 lines" in doc, f"{path.relative_to(ROOT)} has {lines} lines and does not say why at its top"


def test_the_optics_import_nothing_above_them():
    allowed = ("uwcam.optics", "uwcam.compute", "uwcam.fileio")
    for path in sorted((PACKAGE / "optics").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("uwcam"):
                assert node.module.startswith(allowed), f"{path.name} imports {node.module}"
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("uwcam"):
                        assert alias.name.startswith(allowed), f"{path.name} imports {alias.name}"
