"""Profiles and rig files: round trips, and one clear sentence for every problem."""

import numpy as np
import pytest
import yaml

from tests.synthetic import make_profile
from uwcam.fileio import UserInputError
from uwcam.calibration.profile import load_profile, profile_from_mapping, save_profile
from uwcam.calibration.rig import Spectrum, builtin_rig_path, load_rig, resolve_reflectance


@pytest.fixture
def profile_file(tmp_path):
    path = tmp_path / "p.yaml"
    save_profile(make_profile([0.46, 0.11, 0.06], [0.0, 0.2, 0.3], read_noise=2.0), path)
    return path


def test_profile_round_trip(profile_file):
    again = load_profile(profile_file)
    assert again.channel_names == ["R", "G", "B"]
    np.testing.assert_allclose(again.array("attenuation_difference"), [0.0, -0.35, -0.40])
    assert yaml.safe_load(profile_file.read_text())["version"] == 2


def edit(path, change):
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data))


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["channels"][1].update(read_noise=-1), r"key 'channels\.1\.read_noise': Input should be greater than or equal to 0 \(got -1\)"),
        (lambda d: d.update(colour="blue"), r"key 'colour': unknown key; remove it or check its spelling"),
        (lambda d: d.pop("saturation_level"), r"key 'saturation_level': required key is missing"),
        (lambda d: d.update(version=7), r"profile version 7 is newer than this uwcam understands \(2\); upgrade uwcam"),
        (lambda d: d.update(format="something"), r"key 'format' must be 'uwcam-calibration-profile'"),
        (lambda d: d.update(reference_channel="X"), r"reference_channel 'X' is not one of the channels \['R', 'G', 'B'\]"),
        (lambda d: d["channels"][1].update(name="R"), r"channel names must be unique"),
        (lambda d: d.update(channels=d["channels"][:1]), r"key 'channels': List should have at least 2 items"),
        (lambda d: d["channels"][2].update(attenuation_difference="fast"), r"key 'channels\.2\.attenuation_difference': Input should be a valid number"),
    ],
)
def test_bad_profiles_are_explained_in_one_sentence(profile_file, change, message):
    edit(profile_file, change)
    with pytest.raises(UserInputError, match=message) as info:
        load_profile(profile_file)
    text = str(info.value)
    assert str(profile_file) in text and "\n" not in text


def test_unreadable_and_non_yaml_profiles(tmp_path):
    with pytest.raises(UserInputError, match="cannot read calibration profile .*missing.yaml"):
        load_profile(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("channels: [unclosed\n")
    with pytest.raises(UserInputError, match=r"is not valid YAML at line \d+, column \d+"):
        load_profile(bad)
    bad.write_text("- a list\n")
    with pytest.raises(UserInputError, match="must be a YAML mapping"):
        load_profile(bad)


def test_saving_over_a_profile_never_leaves_a_partial_file(profile_file, monkeypatch):
    before = profile_file.read_text()
    import uwcam.calibration.profile as prof

    def boom(_):
        raise RuntimeError("disk full")

    monkeypatch.setattr(prof, "profile_to_yaml", boom)
    with pytest.raises(RuntimeError):
        save_profile(load_profile(profile_file), profile_file)
    assert profile_file.read_text() == before
    assert [p.name for p in profile_file.parent.iterdir()] == [profile_file.name]


def test_uploaded_mapping_is_validated_like_a_file():
    with pytest.raises(UserInputError, match="upload: key 'format'"):
        profile_from_mapping({"format": "x"}, "upload")


def test_builtin_rigs_load():
    rig = load_rig(builtin_rig_path("grey-plate"))
    assert rig.plate.black_patch is not None
    assert resolve_reflectance(rig.plate.reflectance, ["R", "G", "B"], [None] * 3, "plate").tolist() == [0.18] * 3
    colour = load_rig(builtin_rig_path("colour-plate"))
    rho = resolve_reflectance(colour.plate.reflectance, ["R", "G", "B"], [675.0, 575.0, 475.0], "plate")
    np.testing.assert_allclose(rho, [0.345, 0.265, 0.17])
    with pytest.raises(UserInputError, match="known rigs: charuco-plate, colour-plate, grey-plate, grey-plate-large-patch"):
        builtin_rig_path("tank")


def test_spectrum_needs_wavelengths_and_coverage():
    spec = Spectrum(wavelength_nm=[400, 700], reflectance=[0.1, 0.4])
    with pytest.raises(UserInputError, match="give --channels NAME:NM"):
        resolve_reflectance(spec, ["R", "G"], [None, 500.0], "plate")
    with pytest.raises(UserInputError, match=r"lie outside it"):
        resolve_reflectance(spec, ["R", "G"], [800.0, 500.0], "plate")
    with pytest.raises(UserInputError, match="lists 2 reflectances but the images have 3 channels"):
        resolve_reflectance([0.1, 0.2], ["R", "G", "B"], [None] * 3, "plate")


def test_bad_rig_file_is_explained(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"format": "uwcam-rig", "version": 1, "name": "x", "plate": {"size_m": [0.5, -1], "reflectance": 0.2}}))
    with pytest.raises(UserInputError, match=r"rig file .*rig.yaml: key 'plate.size_m.1': Input should be greater than 0"):
        load_rig(path)
