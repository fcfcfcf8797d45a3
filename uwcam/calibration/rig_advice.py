"""Which rig the water needs: whether a black patch of this size leaves the calibration as accurate
as uwcam promises in the water the plate was imaged in, and the rig to use where it does not.

In scattering water the plate's forward-scattered light spills into the black patch and is read as
the water's own light, which biases the attenuation differences low; beyond 5 m, where green and
blue carry the range, the ranges read long by about as much (docs/calibration.md, "Black patch size
in scattering water"). The spill grows with how much the water scatters, which the calibration
itself measures (the water's light at the patch over the plate's own light there), and falls with
the patch's size.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

SPILL_SCALE = 0.043
"""Spill offset (share of G − B) per unit of the water's share of the light at the patch, for a
patch 1 m across; it falls as the patch's side to the power :data:`SPILL_EXPONENT`. Fitted to
`bench/black_patch_spill.py` in uwcam's simulated Jerlov IB and II (noise-free, plate at 1 and
2 m, lamp 0.3 m aside): −5.8, −3.0 and −1.8 % of G − B with 5, 10 and 20 cm patches in Jerlov II,
where the water's share of the blue light at the patch at 2 m is 0.107; −1.5 % with 10 cm in
Jerlov IB (share 0.067). The fit gives −5.5, −3.1 and −1.7 % for Jerlov II's 5, 10 and 20 cm, −1.9 %
for IB's 10 cm."""

SPILL_EXPONENT = 0.83

ACCURACY = 0.02
"""The accuracy the water study holds ranges to (median within 2 % at 3–7 m)."""

LARGE_PATCH_RIG = "grey-plate-large-patch"
LARGE_PATCH_SIDE_M = 0.20


def predicted_spill(water_share: float, patch_side_m: float) -> float:
    """The share of the G − B attenuation difference the black patch's spill takes off (≥ 0), for a
    patch ``patch_side_m`` across (its smaller side, metres) where the water's light at the patch is
    ``water_share`` of the plate's own light there (the largest over channels other than the most
    attenuated, at the farthest calibration distance)."""
    if patch_side_m <= 0 or not np.isfinite(water_share):
        return 0.0
    return float(SPILL_SCALE * max(water_share, 0.0) * patch_side_m ** -SPILL_EXPONENT)


def water_share_at_patch(levels: Sequence[np.ndarray], plate_logs: Sequence[np.ndarray],
                         distances_m: Sequence[float], most_attenuated: int) -> float:
    """The water's light at the black patch over the plate's own light there, at the farthest
    distance, in the channels that carry far ranges: every channel but the ``most_attenuated`` (red,
    whose far ranges green and blue take over). levels, plate_logs: (N,) per distance (DN, ln DN)."""
    far = int(np.argmax(distances_m))
    share = np.asarray(levels[far], np.float64) / np.exp(np.asarray(plate_logs[far], np.float64))
    others = [k for k in range(share.size) if k != most_attenuated]
    return float(np.max(share[others])) if others else float(share.max())


def rig_advice(water_share: float, patch_side_m: float) -> str | None:
    """What to tell a user whose calibration's black patch is ``patch_side_m`` across in water whose
    light at the patch is ``water_share`` of the plate's (:func:`water_share_at_patch`); None where
    the patch keeps the calibration within :data:`ACCURACY`."""
    spill = predicted_spill(water_share, patch_side_m)
    if spill <= ACCURACY:
        return None
    text = (f"this water scatters: its light at the black patch is {water_share:.0%} of the plate's, and the plate's "
            f"light it scatters into a {patch_side_m * 100:.0f} cm patch takes about {spill:.0%} off the attenuation "
            f"differences (ranges beyond 5 m read about {spill:.0%} long)")
    large = predicted_spill(water_share, LARGE_PATCH_SIDE_M)
    if patch_side_m < LARGE_PATCH_SIDE_M and large <= ACCURACY:
        return text + f"; calibrate with the {LARGE_PATCH_RIG} rig (a {LARGE_PATCH_SIDE_M * 100:.0f} cm patch: about {large:.0%})"
    return text + ("; no built-in rig keeps it within 2 % in this water: calibrate nearer (e.g. 0.75 and 1.5 m), where "
                   "less water lies between plate and camera, with the largest black patch your plate can carry")


def calibration_rig_advice(details, rig) -> str | None:
    """:func:`rig_advice` for a calibration (:class:`uwcam.calibration.fit.CalibrationDetails`) made
    with ``rig`` (:class:`uwcam.calibration.rig.Rig`, None: a region given by hand, whose size in
    metres is not known); None where it has nothing to say or nothing to go on."""
    patch = None if rig is None else rig.plate.black_patch
    estimates = [(g.distance_m, g.backscatter) for g in details.groups if g.backscatter is not None]
    if patch is None or not estimates:
        return None
    most_attenuated = int(np.argmax(details.profile.array("attenuation_difference")))
    share = water_share_at_patch([e.level for _, e in estimates], [e.plate_log for _, e in estimates],
                                 [d for d, _ in estimates], most_attenuated)
    return rig_advice(share, float(min(patch.size_m)))
