"""Serial lamp and rangefinders against simulated devices speaking the real protocols on ptys."""

import time

import pytest

from tests.waiting import wait_for
from uwcam.drivers import registry
from uwcam.drivers.base import ConfigurationError, DeviceLost, DriverError, HealthState
from uwcam.drivers.lamp import SerialLamp, load_protocol
from uwcam.drivers.rangefinder import FRESH_WATER, AsciiRangefinder, Ping1DRangefinder, parse_ascii_range
from uwcam.drivers.sim import SimulatedRig
from uwcam.drivers.sim_serial import SimulatedAsciiRanger, SimulatedLampDevice, SimulatedPing1D


# Compile the simulator before any test waits for a frame against a clock.
pytestmark = pytest.mark.usefixtures("warm_kernels")


@pytest.fixture
def rig():
    return SimulatedRig(size=(32, 24), distance=2.5)


def test_lamp_commands_drive_the_device(rig):
    with SimulatedLampDevice(rig) as device:
        lamp = registry.create("lamp", "serial", port=device.path)
        lamp.open()
        lamp.set_intensity(40)
        lamp.on()
        assert rig.lamp_on and rig.lamp_intensity == pytest.approx(0.4)
        status = lamp.status()
        assert status.on and status.percent == 40 and status.temperature_c == pytest.approx(21.5) and status.fault is None
        lamp.off()
        assert not rig.lamp_on and not lamp.status().on
        device.fault = "OVERTEMP"
        assert lamp.status().fault == "OVERTEMP"
        assert lamp.health.state == HealthState.RECOVERING and "OVERTEMP" in lamp.health.reason
        with pytest.raises(ConfigurationError, match="lamp intensity must be 0–100 %, got 120"):
            lamp.set_intensity(120)
        lamp.close()


def test_lamp_survives_a_truncated_reply_and_reports_refusals(rig):
    with SimulatedLampDevice(rig) as device:
        lamp = SerialLamp(device.path)
        device.truncate_next_reply()
        lamp.on()  # first reply cut short: retried once, then fine
        assert lamp.health.state == HealthState.OK
        with pytest.raises(DriverError, match="lamp refused 'PWM 5x': bad number"):
            lamp._transaction("PWM 5x", lamp._ok)
        lamp.close()


def test_lamp_disconnect_then_reconnect(rig):
    with SimulatedLampDevice(rig) as device:
        lamp = SerialLamp(device.path)
        lamp.on()
        device.disconnect()
        with pytest.raises(DeviceLost):
            lamp.off()
        assert lamp.health.state == HealthState.RECOVERING
        device.reconnect()
        assert wait_for(lambda: _try(lamp.off))
        assert not rig.lamp_on and lamp.health.state == HealthState.OK
        lamp.close()


def _try(action):
    try:
        action()
        return True
    except DeviceLost:
        return False


def test_lamp_configuration_errors(tmp_path):
    with pytest.raises(ConfigurationError, match="unknown lamp protocol 'disco'; built in: generic-dimmable-led"):
        load_protocol("disco")
    bad = tmp_path / "lamp.yaml"
    bad.write_text("format: uwcam-lamp-protocol\nversion: 1\nname: x\ncommands: {switch_on: A, switch_off: B, intensity: C, status: D}\n"
                   "replies: {ok: '^OK$', status: '^(unclosed'}\n")
    with pytest.raises(ConfigurationError, match=r"key 'replies.status': not a valid regular expression"):
        load_protocol(str(bad))
    with pytest.raises(ConfigurationError, match="cannot open serial port /dev/ttyNOPE"):
        SerialLamp("/dev/ttyNOPE").open()


@pytest.mark.parametrize("style", ["nmea", "mm"])
def test_ascii_rangefinder_reads_and_rescales_speed_of_sound(rig, style):
    with SimulatedAsciiRanger(rig, style=style, rate_hz=50) as device:
        with AsciiRangefinder(device.path, speed_of_sound=1500.0) as salt:
            assert wait_for(lambda: salt.stats.readings >= 3)
            assert salt.latest().range_m == pytest.approx(2.5, abs=0.002)
            assert salt.latest().confidence is None  # these devices give no figure of their own
        with AsciiRangefinder(device.path, speed_of_sound=FRESH_WATER) as fresh:
            assert wait_for(lambda: fresh.stats.readings >= 3)
            assert fresh.latest().range_m == pytest.approx(2.5 * FRESH_WATER / 1500.0, abs=0.002)


def test_ascii_rangefinder_shrugs_off_garbage_and_recovers(rig):
    with SimulatedAsciiRanger(rig, rate_hz=50) as device, AsciiRangefinder(device.path, stale_after_s=0.3) as rf:
        assert wait_for(lambda: rf.stats.readings >= 2)
        device.send_garbage()
        device.send(b"$SDDPT,1.000,0.0*00\r\n")  # wrong checksum
        assert wait_for(lambda: rf.stats.garbage >= 2)
        assert wait_for(lambda: rf.health.state == HealthState.OK)
        device.silent = True
        assert wait_for(lambda: rf.health.state == HealthState.RECOVERING)
        assert "no valid range" in rf.health.reason and rf.fresh() is None
        device.silent = False
        device.disconnect()
        time.sleep(0.3)
        device.reconnect()
        before = rf.stats.readings
        assert wait_for(lambda: rf.stats.readings > before + 2)
        assert rf.health.state == HealthState.OK and rf.fresh() is not None


def test_rangefinder_limits_reject_readings(rig):
    with SimulatedAsciiRanger(rig, rate_hz=50) as device, AsciiRangefinder(device.path, max_range_m=2.0) as rf:
        assert wait_for(lambda: rf.stats.rejected >= 3)
        assert rf.stats.readings == 0 and rf.latest() is None
    with pytest.raises(ConfigurationError, match="speed of sound 340.0 m/s is not water's"):
        AsciiRangefinder("/dev/null", speed_of_sound=340.0)


def test_ping1d_reads_distance_and_confidence(rig):
    with SimulatedPing1D(rig, confidence=97) as device, Ping1DRangefinder(device.path, speed_of_sound=1500.0, rate_hz=50) as rf:
        assert wait_for(lambda: rf.stats.readings >= 3)
        reading = rf.latest()
        assert reading.range_m == pytest.approx(2.5, abs=0.002) and reading.confidence == pytest.approx(0.97)
        assert device.speed_of_sound == 1500.0


def test_ping1d_is_told_the_speed_of_sound_and_filters_confidence(rig):
    with SimulatedPing1D(rig, confidence=40) as device:
        with Ping1DRangefinder(device.path, speed_of_sound=FRESH_WATER, rate_hz=50) as rf:
            assert wait_for(lambda: rf.stats.readings >= 2)
            assert device.speed_of_sound == FRESH_WATER
            # The water is salt (1500 m/s), the sonar told fresh: it reports short, as a real one would.
            assert rf.latest().range_m == pytest.approx(2.5 * FRESH_WATER / 1500.0, abs=0.002)
        with Ping1DRangefinder(device.path, min_confidence=0.8, rate_hz=50) as picky:
            assert wait_for(lambda: picky.stats.rejected >= 2)
            assert picky.latest() is None


def test_ping1d_recovers_from_garbage_and_disconnection(rig):
    with SimulatedPing1D(rig) as device, Ping1DRangefinder(device.path, rate_hz=50) as rf:
        assert wait_for(lambda: rf.stats.readings >= 2)
        device.send_garbage(b"BR\xff\xff\x00\x00junk")
        device.disconnect()
        assert wait_for(lambda: rf.health.state == HealthState.RECOVERING)
        device.reconnect()
        before = rf.stats.readings
        assert wait_for(lambda: rf.stats.readings > before + 2)
        assert rf.health.state == HealthState.OK
        assert device.speed_of_sound == 1500.0  # re-told after reconnecting


def test_ascii_parsing():
    assert parse_ascii_range("R1234") == 1.234
    assert parse_ascii_range("$SDDPT,12.5,0.0*67") is None  # checksum wrong
    body = "SDDBT,41.0,f,12.50,M,6.8,F"
    checksum = 0
    for ch in body:
        checksum ^= ord(ch)
    assert parse_ascii_range(f"${body}*{checksum:02X}") == 12.5
    assert parse_ascii_range("hello") is None
    assert parse_ascii_range("R12a4") is None


def test_simulated_rig_through_the_registry_is_consistent():
    """Camera, lamp and rangefinder from the registry share one world, over the real serial code."""
    from uwcam.drivers.supervisor import SupervisedCamera

    rig = SimulatedRig(size=(32, 24), distance=3.0)
    lamp = registry.create("lamp", "sim", rig=rig)
    ranger = registry.create("rangefinder", "sim-ping1d", rig=rig, rate_hz=50)
    camera = SupervisedCamera(registry.create("camera", "sim", rig=rig, fps=100.0, serial_number="SIM-RIG"))
    try:
        with camera, ranger:
            lit = camera.get(5.0).data.mean()
            lamp.off()
            # A frame being rendered when the lamp went off may still come, lit and labelled lit;
            # every frame's label must match its light, and dark ones must follow.
            deadline = time.monotonic() + 5.0
            while (frame := camera.get(5.0)).lamp_on is not False and time.monotonic() < deadline:
                assert frame.data.mean() > 0.5 * lit, "a frame labelled lit is dark"
            assert frame.lamp_on is False and frame.data.mean() < 0.1 * lit
            assert wait_for(lambda: ranger.fresh() is not None)
            assert ranger.fresh().range_m == pytest.approx(rig.true_range(), abs=0.002)
            assert rig.true_range() == pytest.approx(3.0, abs=0.01)  # the centre pixel, a hair off the axis
    finally:
        lamp.close()
    assert {"serial", "sim"} <= set(registry.known("lamp"))
    assert {"ascii", "ping1d", "sim-ascii", "sim-ping1d"} <= set(registry.known("rangefinder"))
