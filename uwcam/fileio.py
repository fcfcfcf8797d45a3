"""Small shared helpers for files: atomic writes and one-sentence YAML/pydantic errors."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import yaml
from pydantic import ValidationError


class UserInputError(Exception):
    """Bad input from a person or a file: the message says what is wrong and what to do."""


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO[Any]]:
    """Write ``path`` via a temporary file in the same folder, fsync, then rename.

    Readers never see a half-written file, and on any error the old file (if any)
    is untouched and no partial output is left behind.
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent or ".")
    os.close(fd)  # reopened by name: some writers (numpy, tifffile) want a named file
    try:
        with open(tmp, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
"""libyaml's parser where PyYAML has it (about 9× less CPU than the pure-Python one: a 1 MB
profile upload held the interpreter for seconds and the frame rate fell), the same safe types."""


class UniqueKeyLoader(SAFE_LOADER):  # type: ignore[misc, valid-type]
    """:data:`SAFE_LOADER` that refuses a key given twice in one mapping. PyYAML would keep the
    last silently (an ``api:`` section written twice loses the first), and strict parsers (BlueOS's,
    YAML 1.2's) refuse such a file; a key that a merge (``<<: *anchor``) brings in may still be
    given again, as YAML intends."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, yaml.Mark] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark)
                except TypeError:  # unhashable: the constructor below says so
                    continue
                if first is not key_node.start_mark:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping", node.start_mark,
                        f"key {key!r} is given twice (first at line {first.line + 1}); keep one", key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


# YAML 1.1 (PyYAML's) reads a number without a dot, such as 1e-5, as a string; YAML 1.2 and JSON read
# it as a number, and users write it so. Numbers are strict where users give them (a string is refused,
# not coerced), so read those as floats.
UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def safe_load(text: str | bytes) -> Any:
    """``yaml.safe_load`` with :data:`SAFE_LOADER`, refusing duplicate keys (:class:`UniqueKeyLoader`)."""
    return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 (a safe loader)


def load_yaml_mapping(path: str | os.PathLike[str], what: str) -> dict[str, Any]:
    """Read a YAML file that must hold a mapping; errors name the file and the problem."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise UserInputError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise UserInputError(f"{what} {path} is not a UTF-8 text file; give a YAML file") from None
    try:
        data = safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise UserInputError(f"{what} {path} is not valid YAML{where}: {problem}") from None
    if not isinstance(data, dict):
        raise UserInputError(f"{what} {path} must be a YAML mapping of keys to values, found {type(data).__name__}")
    return data


def explain_validation_error(exc: ValidationError, source: str) -> str:
    """One sentence for the first problem pydantic found: the key path, what it got, what it needs."""
    err = exc.errors()[0]
    key = ".".join(str(p) for p in err["loc"])
    message = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        message = "unknown key; remove it or check its spelling"
    elif err["type"] == "missing":
        message = "required key is missing"
    elif "input" in err and not isinstance(err["input"], (dict, list)):
        message = f"{message} (got {err['input']!r})"
    more = f" (and {len(exc.errors()) - 1} more problem(s))" if len(exc.errors()) > 1 else ""
    where = f"key '{key}': " if key else ""
    return f"{source}: {where}{message}{more}"
