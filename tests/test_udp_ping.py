"""The ping1d rangefinder reading a Ping1D bridged over UDP, as BlueOS's ping service serves it.

The sonar is the simulated Ping1D speaking the real ping protocol on a pseudo-terminal; a
serial-to-UDP bridge (like BlueOS's) shares it on a loopback port; the driver under test talks
``udp:127.0.0.1:PORT``.
"""

import time

import pytest

from tests.waiting import wait_for
from uwcam.drivers.base import ConfigurationError, HealthState
from uwcam.drivers.rangefinder import FRESH_WATER, Ping1DRangefinder
from uwcam.drivers.sim import SimulatedRig
from uwcam.drivers.sim_serial import SimulatedPing1D
from uwcam.drivers.udp_bridge import SerialUdpBridge
from uwcam.drivers.udp_link import parse_udp_address


@pytest.fixture
def rig():
    return SimulatedRig(size=(32, 24), distance=2.5)


def test_reads_a_bridged_ping_and_tells_it_the_speed_of_sound(rig):
    with SimulatedPing1D(rig, confidence=93) as device, SerialUdpBridge(device.path) as bridge:
        with Ping1DRangefinder(bridge.address, speed_of_sound=FRESH_WATER, rate_hz=50) as rf:
            assert wait_for(lambda: rf.stats.readings >= 3)
            assert device.speed_of_sound == FRESH_WATER
            reading = rf.latest()
            # The water is salt (1500 m/s), the sonar was told fresh: it reports short.
            assert reading.range_m == pytest.approx(2.5 * FRESH_WATER / 1500.0, abs=0.002)
            assert reading.confidence == pytest.approx(0.93) and rf.health.state == HealthState.OK


def test_two_clients_share_one_sonar(rig):
    """uwcam and another client (BlueOS's own MAVLink driver, Ping Viewer) on one bridge."""
    with SimulatedPing1D(rig) as device, SerialUdpBridge(device.path) as bridge:
        with Ping1DRangefinder(bridge.address, rate_hz=20) as a, Ping1DRangefinder(bridge.address, rate_hz=20) as b:
            assert wait_for(lambda: a.stats.readings >= 5 and b.stats.readings >= 5)
            assert a.latest().range_m == pytest.approx(2.5, abs=0.002) == b.latest().range_m


def test_garbage_and_silence_are_survived(rig):
    with SimulatedPing1D(rig) as device, SerialUdpBridge(device.path) as bridge:
        # Stale after 1 s, lost after 3 s: a loaded test machine can hold a reply back for a few
        # tenths of a second, which must not read as silence.
        with Ping1DRangefinder(bridge.address, rate_hz=50, stale_after_s=1.0, lost_after_s=3.0) as rf:
            assert wait_for(lambda: rf.stats.readings >= 2)
            device.send_garbage(b"BR\xff\xff\x00\x00junk\x00\xffBR")  # between replies: dropped
            device.truncate_next_reply()  # half a reply, then the next one: a bad checksum
            assert wait_for(lambda: rf.stats.garbage >= 1)
            before = rf.stats.readings
            assert wait_for(lambda: rf.stats.readings > before + 2 and rf.health.state == HealthState.OK)
            bridge.silent = True  # datagrams vanish both ways
            assert wait_for(lambda: rf.health.state == HealthState.RECOVERING, 10.0)
            assert "no valid range" in rf.health.reason and rf.fresh() is None
            assert wait_for(lambda: rf.health.state == HealthState.LOST, 10.0)
            assert "nothing valid for" in rf.health.reason
            bridge.silent = False
            before = rf.stats.readings
            assert wait_for(lambda: rf.stats.readings > before + 2 and rf.health.state == HealthState.OK, 10.0)


def test_a_vanished_bridge_is_reported_and_found_again(rig):
    with SimulatedPing1D(rig) as device:
        bridge = SerialUdpBridge(device.path).start()
        port = bridge.port
        with Ping1DRangefinder(bridge.address, rate_hz=50) as rf:
            try:
                assert wait_for(lambda: rf.stats.readings >= 2)
                bridge.stop()  # the ping service went away: nothing listens on the port
                assert wait_for(lambda: "connection refused" in rf.health.reason, 5.0), rf.health
                assert rf.health.state == HealthState.RECOVERING
                time.sleep(0.3)
                bridge = SerialUdpBridge(device.path, port=port).start()  # it comes back on its port
                before = rf.stats.readings
                assert wait_for(lambda: rf.stats.readings > before + 2, 15.0)
                assert rf.health.state == HealthState.OK
                assert device.speed_of_sound == 1500.0
            finally:
                bridge.stop()


def test_bad_udp_addresses_are_refused():
    for bad in ("udp:127.0.0.1", "udp::9090", "udp:127.0.0.1:0", "udp:127.0.0.1:99999", "udp:host:port"):
        with pytest.raises(ConfigurationError, match="is not udp:HOST:PORT"):
            Ping1DRangefinder(bad)
    assert parse_udp_address("udp:[::1]:9090") == ("::1", 9090)
    rf = Ping1DRangefinder("udp:no-such-host.invalid:9090")
    with pytest.raises(ConfigurationError, match="cannot resolve no-such-host.invalid"):
        rf.start()
