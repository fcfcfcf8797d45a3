"""Water per channel: beam attenuation c, scattered-light attenuation G, forward blur B, backscatter β.

Jerlov presets come from the published inherent optical properties carried by the
``jerlov`` package (absorption a and scattering b at each channel's centre wavelength):

* c = a + b, the beam attenuation of unscattered light;
* G = a + b_b, the attenuation of forward-scattered light, which stays in the beam and is
  lost only to absorption and backscattering (b_b = 0.0183·b, the Petzold average-particle
  backscatter ratio);
* β = χ·b_b / 2π, the volume scattering function near 180° (χ from Boss & Pegau 2001 at
  170°, the largest angle they tabulate), in 1/(m·sr);
* B, the forward blur of McGlamery's OTF exp(−B·d·f), is empirical; presets use 0.005.

Sources: Williamson & Hollins (2022, measured) for types IB, II, III, 1C, 3C, 5C;
Solonenko & Mobley (2015) for I, IA, 7C, 9C, which the measurements do not cover.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import jerlov
import numpy as np
from numpy.typing import NDArray

from uwcam.fileio import UserInputError

# The study water of the method's original simulations: R/G/B effective attenuation.
IDEAL_WAVELENGTHS_NM = (475.0, 575.0, 675.0)
IDEAL_ATTENUATION = (0.06, 0.11, 0.46)

BACKSCATTER_RATIO = 0.0183  # Petzold average particle b_b/b
DEFAULT_FORWARD_BLUR = 0.005
_MEASURED = ("IB", "II", "III", "1C", "3C", "5C")
_JERLOV_TYPES = ("I", "IA", "IB", "II", "III", "1C", "3C", "5C", "7C", "9C")

WATER_PRESETS: dict[str, str] = {
    "ideal": "c = 0.06/0.11/0.46 1/m at 475/575/675 nm (interpolated), no scattering: the method's textbook water",
    **{f"jerlov-{t}": f"Jerlov {t} from {'Williamson & Hollins 2022' if t in _MEASURED else 'Solonenko & Mobley 2015'}"
       for t in _JERLOV_TYPES},
}


@dataclass(frozen=True)
class Water:
    """Optical properties per channel (arrays of shape (N,))."""

    name: str
    attenuation: NDArray[np.float64]
    """c, beam attenuation, 1/m."""
    scatter_attenuation: NDArray[np.float64]
    """G, attenuation of forward-scattered light, 1/m (G ≤ c; G = c means no forward scatter)."""
    forward_blur: float
    """B, dimensionless: the forward-scatter OTF is exp(−B·d·f), f in cycles/rad, d in m."""
    backscatter: NDArray[np.float64]
    """β, volume scattering function toward the camera, 1/(m·sr)."""
    notes: tuple[str, ...] = field(default=())
    """Caveats of the data the preset rests on."""

    def with_overrides(
        self,
        forward_blur: float | None = None,
        scatter_attenuation: NDArray | float | None = None,
        backscatter: NDArray | float | None = None,
        attenuation: NDArray | float | None = None,
    ) -> "Water":
        n = len(self.attenuation)
        out = self
        if attenuation is not None:
            out = replace(out, attenuation=np.broadcast_to(np.asarray(attenuation, float), (n,)).copy())
        if forward_blur is not None:
            out = replace(out, forward_blur=float(forward_blur))
        if scatter_attenuation is not None:
            out = replace(out, scatter_attenuation=np.broadcast_to(np.asarray(scatter_attenuation, float), (n,)).copy())
        if backscatter is not None:
            out = replace(out, backscatter=np.broadcast_to(np.asarray(backscatter, float), (n,)).copy())
        if np.any(out.scatter_attenuation > out.attenuation + 1e-12):
            raise UserInputError("scatter attenuation G must not exceed the beam attenuation c in any channel")
        if out.forward_blur < 0 or np.any(out.backscatter < 0) or np.any(out.attenuation < 0):
            raise UserInputError("forward blur, backscatter and attenuation must not be negative")
        return out


def water_preset(name: str, wavelengths_nm: list[float]) -> Water:
    """A named preset evaluated at the channels' centre wavelengths (nm)."""
    if name not in WATER_PRESETS:
        raise UserInputError(f"unknown water '{name}'; known: {', '.join(WATER_PRESETS)}")
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if name == "ideal":
        c = np.interp(wl, IDEAL_WAVELENGTHS_NM, IDEAL_ATTENUATION)
        return Water(name, c, c.copy(), 0.0, np.zeros_like(c))
    jtype = name.removeprefix("jerlov-")
    source = "williamson2022" if jtype in _MEASURED else "solonenko2015"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        w = jerlov.water(jtype, source=source)
        lo, hi = w.range_nm
        if np.any(wl < lo) or np.any(wl > hi):
            raise UserInputError(f"{name} data cover {lo:g}–{hi:g} nm; channel wavelengths {list(wl)} fall outside")
        a = np.array([float(w.a(x)) for x in wl])
        b = np.array([float(w.b(x)) for x in wl])
        chi = float(jerlov.particulate_chi(170.0))
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise UserInputError(f"{name} has no published absorption at some of the wavelengths {list(wl)}; choose another type")
    bb = BACKSCATTER_RATIO * b
    notes = tuple(sorted({str(m.message) for m in caught}))
    return Water(name, a + b, a + bb, DEFAULT_FORWARD_BLUR, chi * bb / (2 * np.pi), notes)
