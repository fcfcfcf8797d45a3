"""Without open-water frames the water's light is known at the black patch's pixel only; elsewhere the
lamp's beam and the lens's shading, which the patch cannot see, move it. The doubt on it grows with
the angle from the patch's ray (#41): a lamp with a Gaussian beam, which uwcam's model takes as even,
no longer leaves valid pixels beyond 3σ."""

from __future__ import annotations

import numpy as np

from uwcam.optics.geometry import Intrinsics


def test_the_doubt_is_one_minus_cos4_of_the_angle_from_the_patch_s_ray():
    from uwcam.calibration.rig import builtin_rig_path, load_rig
    from uwcam.simulation import CameraModel, Lamp, water_preset
    from uwcam.simulation.tank import calibrate_in_simulation
    from uwcam.water.backscatter import BackscatterModel

    profile = calibrate_in_simulation(water_preset("jerlov-II", [675.0, 575.0, 475.0]), Lamp(position=(0.3, 0.0, 0.0)),
                                      (160, 120), CameraModel(), frames_per_distance=1,
                                      rig=load_rig(builtin_rig_path("grey-plate")))  # its patch in a corner
    model = BackscatterModel.from_profile(profile, shape=(120, 160))
    k = profile.intrinsics
    intr = Intrinsics(**k)
    x, y = (int(round(v)) for v in profile.backscatter.patch_pixels[-1])
    # The angle between two pixels' rays, from the pinhole geometry written out here.
    def ray(px, py):
        v = np.array([(px - intr.cx) / intr.fx, (py - intr.cy) / intr.fy, 1.0])
        return v / np.linalg.norm(v)

    for px, py in ((0, 0), (159, 119), (80, 60), (x, y)):
        cos = float(ray(px, py) @ ray(x, y))
        assert abs(model.spread_doubt[py, px] - (1.0 - cos**4)) < 1e-9
    assert model.spread_doubt[y, x] < 1e-9
    with_open_water = BackscatterModel.from_profile(profile, np.full((120, 160, 3), 500.0))
    assert with_open_water.spread_doubt is None  # the open water measured the light across the view


def test_a_gaussian_beam_no_longer_leaves_pixels_beyond_3_sigma_without_open_water(tmp_path):
    """The independent forward model (bench/independent_world.py: Jerlov II-like, a point lamp 0.3 m
    aside with a 30° Gaussian beam), calibrated and ranged through the command line, a seabed at 3 m,
    no open-water frame, 4 frames fused: before the doubt, 12.4 % of the valid pixels lay beyond 3σ
    (z sd 1.95)."""
    import os
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))
    import independent_world as iw

    from uwcam.calibration.rig import builtin_rig_path
    from uwcam.cli import main

    water = iw.WATERS["jerlov-II-like"]
    camera = iw.Camera(width=160, height=120)
    lamp = iw.Lamp(position_m=(0.3, 0.0, 0.0), sigma_beam_deg=30.0)
    layout = iw.plate_from_rig(str(builtin_rig_path("grey-plate-large-patch")))
    images, exposure = [], None
    for d in (1.0, 2.0):
        plate = iw.render(camera, iw.Scene("plate", d, layout), lamp, water, exposure=exposure)
        exposure = plate.exposure
        for k, f in enumerate(plate.frames(camera, 4, seed=int(10 * d))):
            images.append(str(tmp_path / f"plate_{d:g}_{k}.npy"))
            np.save(images[-1], f)
    fx, fy, cx, cy = camera.intrinsics
    profile = str(tmp_path / "p.yaml")
    args = ["calibrate", *images]
    for d in (1.0, 2.0):
        args += ["--distance", f"{d:g}"] * 4
    args += ["--rig", "grey-plate-large-patch", "--intrinsics", f"{fx:.6f},{fy:.6f},{cx:g},{cy:g}",
             "--lamp-offset", "0.3,0,0", "--lamp-radius", "0", "--dark-level", ",".join([f"{camera.dark_level_dn:g}"] * 3),
             "--channels", "R:650,G:520,B:470", "-o", profile]
    assert main(args) == 0
    seabed = iw.render(camera, iw.Scene("seabed", 3.0), lamp, water, exposure=exposure)
    frames = []
    for k, f in enumerate(seabed.frames(camera, 4, seed=3)):
        frames.append(str(tmp_path / f"seabed_{k}.npy"))
        np.save(frames[-1], f)
    out, var = str(tmp_path / "r.npy"), str(tmp_path / "v.npy")
    assert main(["range", profile, *frames, "-o", out, "--variance", var, "--compensate-backscatter",
                 "--smoothing", "mean", "--path-bounds", "0,100"]) == 0
    r, v, truth = np.load(out), np.load(var), seabed.truth_m
    inner = np.zeros(truth.shape, bool)
    inner[12:108, 16:144] = True
    valid = np.isfinite(r) & inner
    z = (r[valid] - truth[valid]) / np.sqrt(v[valid])
    assert valid.sum() > 0.9 * inner.sum()
    assert np.mean(np.abs(z) > 3.0) <= 0.02, (np.mean(np.abs(z) > 3.0), np.std(z))
