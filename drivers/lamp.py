"""Lamps on a serial line, driven from a YAML protocol description (drivers/lamp_protocols/).

A new lamp needs a YAML file, not code: command templates, reply patterns, baud rate,
terminator and timeout. Every command waits for its reply; a garbled or missing reply is
retried once, then reported, and the lamp's health says why.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from uwcam.drivers.options import DriverOptions, Whole
from uwcam.drivers.base import ConfigurationError, DeviceLost, DriverError, Health, HealthState
from uwcam.drivers.serial_link import SerialLink
from uwcam.fileio import UserInputError, explain_validation_error, load_yaml_mapping


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LampCommands(_Strict):
    # Not "on"/"off": YAML 1.1 reads those keys as booleans.
    switch_on: str
    switch_off: str
    intensity: str
    """Template with {percent} (0–100)."""
    status: str


class LampReplies(_Strict):
    ok: str
    status: str
    """Needs named groups state and percent; may have temperature_c and fault."""
    error: str = "^ERR (?P<reason>.*)$"

    @field_validator("ok", "status", "error")
    @classmethod
    def _compiles(cls, value: str) -> str:
        try:
            re.compile(value)
        except re.error as exc:
            raise ValueError(f"not a valid regular expression: {exc}") from None
        return value


class LampProtocol(_Strict):
    format: Literal["uwcam-lamp-protocol"]
    version: Literal[1]
    name: str
    baud: Annotated[int, Field(gt=0)] = 115200
    terminator: str = "\r\n"
    timeout_s: Annotated[float, Field(gt=0, le=10)] = 0.5
    commands: LampCommands
    replies: LampReplies


def load_protocol(name_or_path: str) -> LampProtocol:
    """A protocol by built-in name (e.g. generic-dimmable-led) or path to a YAML file."""
    path = Path(name_or_path)
    if not path.exists():
        path = Path(str(resources.files("uwcam.drivers").joinpath("lamp_protocols", f"{name_or_path}.yaml")))
        if not path.exists():
            known = sorted(p.stem for p in path.parent.glob("*.yaml"))
            raise ConfigurationError(f"unknown lamp protocol '{name_or_path}'; built in: {', '.join(known)}, or give a YAML path")
    try:
        return LampProtocol.model_validate(load_yaml_mapping(path, "lamp protocol"))
    except ValidationError as exc:
        raise ConfigurationError(explain_validation_error(exc, f"lamp protocol {path}")) from None
    except UserInputError as exc:
        raise ConfigurationError(str(exc)) from None


@dataclass(frozen=True)
class LampStatus:
    on: bool
    percent: int
    temperature_c: float | None = None
    fault: str | None = None


class SerialLamp:
    class Options(DriverOptions):
        port: str
        """Serial port, preferably a stable udev name (see deploy/99-uwcam.rules)."""
        protocol: str = "generic-dimmable-led"
        """Built-in protocol name (drivers/lamp_protocols/) or path of a protocol YAML file."""
        baud: Annotated[Whole, Field(gt=0, le=10_000_000)] | None = None
        """Overrides the protocol's baud rate."""

    """A lamp speaking a line protocol on a serial port."""

    kind = "serial"

    def __init__(self, port: str, protocol: str = "generic-dimmable-led", baud: int | None = None) -> None:
        self.protocol = load_protocol(protocol)
        self.link = SerialLink(port, baud or self.protocol.baud, self.protocol.timeout_s)
        self._term = self.protocol.terminator.encode()
        self._status = re.compile(self.protocol.replies.status)
        self._ok = re.compile(self.protocol.replies.ok)
        self._error = re.compile(self.protocol.replies.error)
        self.last_status: LampStatus | None = None

    @property
    def health(self) -> Health:
        return self.link.health.current

    def open(self) -> None:
        self.link.check_exists()

    def _transaction(self, command: str, expect: re.Pattern) -> re.Match:
        reason = ""
        with self.link.lock:
            for _ in range(2):  # one retry: a single garbled line should not fail a command
                self.link.write(command.encode() + self._term)
                line = self.link.read_until(self._term)
                text = line.removesuffix(self._term).decode(errors="replace").strip()
                if not line.endswith(self._term):
                    reason = f"no complete reply to '{command}' within {self.protocol.timeout_s:g} s (got {text!r})"
                    continue
                match = expect.match(text)
                if match:
                    self.link.health.set(HealthState.OK, "answering")
                    return match
                error = self._error.match(text)
                if error:
                    raise DriverError(f"lamp refused '{command}': {error.groupdict().get('reason', text)}")
                reason = f"unexpected reply to '{command}': {text!r}"
            self.link.fail(reason)  # still holding the lock: never close under another caller's transaction
        raise DeviceLost(reason)

    def on(self) -> None:
        self._transaction(self.protocol.commands.switch_on, self._ok)
        self._remember(on=True)

    def off(self) -> None:
        self._transaction(self.protocol.commands.switch_off, self._ok)
        self._remember(on=False)

    def _remember(self, **change) -> None:
        """Keep last_status current after a command the lamp acknowledged."""
        last = self.last_status or LampStatus(on=False, percent=100)
        self.last_status = LampStatus(**{**last.__dict__, **change})

    def set_intensity(self, percent: float) -> None:
        if not 0 <= percent <= 100:
            raise ConfigurationError(f"lamp intensity must be 0–100 %, got {percent}")
        self._transaction(self.protocol.commands.intensity.format(percent=int(round(percent))), self._ok)
        self._remember(percent=int(round(percent)))

    def status(self) -> LampStatus:
        m = self._transaction(self.protocol.commands.status, self._status).groupdict()
        temp = m.get("temperature_c")
        self.last_status = LampStatus(m["state"].upper() == "ON", int(m["percent"]),
                                      float(temp) if temp is not None else None, m.get("fault"))
        if self.last_status.fault:
            self.link.health.set(HealthState.RECOVERING, f"lamp reports fault {self.last_status.fault}")
        return self.last_status

    def close(self) -> None:
        self.link.close()
