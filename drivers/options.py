"""Driver options: every driver declares what its ``options:`` in the configuration may hold.

A driver class has an ``Options`` pydantic model (unknown keys refused, numbers finite and in
range); ``uwcam config check`` and the daemon validate a rig's options against it before any
device is touched, so a misspelt option is an error, not silently ignored. A driver without
one (a third-party plug-in) is checked against its ``__init__`` signature instead.
"""

from __future__ import annotations

import inspect
import typing
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, create_model

from uwcam.drivers.base import ConfigurationError

Real = Annotated[float, Strict(), Field(allow_inf_nan=False)]
"""A finite number; NaN, ±Infinity, booleans and strings are refused."""
Whole = Annotated[int, Strict()]
Flag = Annotated[bool, Strict()]
ChannelNames = Annotated[list[Annotated[str, Field(min_length=1, max_length=32)]], Field(min_length=1, max_length=16)]


class DriverOptions(BaseModel):
    """Base of every driver's ``Options``: unknown keys and non-finite numbers are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


INJECTED = frozenset({"self", "rig"})
"""Constructor arguments the daemon supplies itself (the shared simulated rig), not options."""


def options_model(cls: type) -> type[BaseModel]:
    """The class's own ``Options``, or a model built from its ``__init__`` signature."""
    own = cls.__dict__.get("Options")
    if isinstance(own, type) and issubclass(own, BaseModel):
        return own
    try:
        hints = typing.get_type_hints(cls.__init__)
    except Exception:  # unresolvable annotations: accept anything of that name
        hints = {}
    fields: dict[str, Any] = {}
    open_ended = False
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name in INJECTED or p.kind is p.VAR_POSITIONAL:
            continue
        if p.kind is p.VAR_KEYWORD:
            # Options passed on to a simulated rig are set under `simulation:` when the daemon
            # shares one rig; elsewhere an open-ended driver takes what it is given.
            open_ended = "rig" not in inspect.signature(cls.__init__).parameters
            continue
        annotation = hints.get(name, Any)
        fields[name] = (annotation, ... if p.default is p.empty else p.default)
    config = ConfigDict(extra="allow" if open_ended else "forbid", allow_inf_nan=False, arbitrary_types_allowed=True)
    return create_model(f"{cls.__name__}Options", __config__=config, **fields)


def check_options(kind: str, name: str, cls: type, options: dict[str, Any]) -> dict[str, Any]:
    """Validated options (only those given); ConfigurationError naming the driver and the key."""
    from uwcam.fileio import explain_validation_error

    model = options_model(cls)
    try:
        validated = model.model_validate(options)
    except ValidationError as exc:
        message = explain_validation_error(exc, f"{kind} driver '{name}' options")
        fields = sorted(model.model_fields)
        raise ConfigurationError(f"{message}; its options are: {', '.join(fields) or 'none'}") from None
    given = validated.model_dump(exclude_unset=True)
    extra = validated.model_extra or {}
    return {**given, **extra}
