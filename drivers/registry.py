"""Driver registry: drivers are found by name through Python entry points.

uwcam's own drivers are declared in its pyproject.toml under the groups ``uwcam.cameras``,
``uwcam.lamps`` and ``uwcam.rangefinders``; a third-party package adds its own drivers the
same way, with no change to uwcam. A driver's module is imported only when it is chosen,
so an SDK that is not installed only matters to the rigs that use it.
"""

from __future__ import annotations

from importlib.metadata import entry_points

from uwcam.drivers.base import ConfigurationError

GROUPS = {"camera": "uwcam.cameras", "lamp": "uwcam.lamps", "rangefinder": "uwcam.rangefinders"}


def known(kind: str) -> list[str]:
    """Names of the drivers of a kind ("camera", "lamp", "rangefinder")."""
    return sorted({ep.name for ep in entry_points(group=GROUPS[kind])})


def driver_class(kind: str, name: str) -> type:
    """The driver class registered as ``name``; ConfigurationError listing the known names if none."""
    if kind not in GROUPS:
        raise ConfigurationError(f"unknown kind of device '{kind}'; known: {', '.join(GROUPS)}")
    matches = [ep for ep in entry_points(group=GROUPS[kind]) if ep.name == name]
    if not matches:
        raise ConfigurationError(f"unknown {kind} driver '{name}'; known {kind} drivers: {', '.join(known(kind))}")
    try:
        return matches[0].load()
    except ImportError as exc:
        raise ConfigurationError(f"{kind} driver '{name}' cannot load: {exc}; install what it needs") from None


def validate_options(kind: str, name: str, options: dict) -> dict:
    """The options validated against the driver's ``Options`` (see :mod:`uwcam.drivers.options`);
    ConfigurationError naming the driver, the key and what is wrong."""
    from uwcam.drivers.options import check_options

    return check_options(kind, name, driver_class(kind, name), options)


def create(kind: str, name: str, **options) -> object:
    """An instance of the named driver, constructed with ``options`` from the configuration."""
    cls = driver_class(kind, name)
    try:
        return cls(**options)
    except TypeError as exc:
        raise ConfigurationError(f"{kind} driver '{name}': {exc}") from None
