"""Optional parts of uwcam: the library each one needs, and one line naming the extra to install.

A camera daemon on a Raspberry Pi ranges, records and serves without these; ``deploy/install.sh``
installs them all by default (``bash deploy/install.sh lean`` leaves them out).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from uwcam.fileio import UserInputError

EXTRAS: dict[str, tuple[str, str]] = {
    # extra: (the module it provides, what it is for)
    "cluster": ("distributed", "reprocessing on a Dask cluster (uwcam reprocess --scheduler)"),
    "reports": ("matplotlib", "calibration reports, plots and plate artwork"),
    "zenoh": ("zenoh", "remote monitoring on Zenoh (the zenoh: section, uwcam monitor)"),
}


def require_extra(extra: str, module: str | None = None) -> ModuleType:
    """Import the module behind ``extra`` (or ``module``, a submodule of it); when it is missing,
    UserInputError in one line naming the extra to install."""
    provided, purpose = EXTRAS[extra]
    try:
        return importlib.import_module(module or provided)
    except ImportError:
        raise UserInputError(f"{purpose} needs the {provided} library, which is not installed: "
                             f"pip install 'uwcam[{extra}]' (deploy/install.sh installs it)") from None
