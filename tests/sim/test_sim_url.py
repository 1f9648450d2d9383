"""``sim://`` scanner URLs: an embedded simulated LMS100 and the real LMS100 client over loopback TCP."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from drivers.errors import DeviceURLError
from drivers.lms100.client import ScannerStateError
from drivers.url import open_device
from sim.scanner import ScannerServer, SimulatorError
from sim.scene import LMS1xxSensor, SensorModel


@pytest.mark.parametrize("cola", ["a", "b"])
def test_sim_url_opens_a_connected_client_and_closes_the_server(cola: str) -> None:
    url = f"sim://?cola={cola}&scene=wall&realtime=0&timeout=2"
    client = open_device("scanner", url, sensor=SensorModel.noiseless())
    server: ScannerServer = client.sim_server
    address = server.address
    try:
        assert client.device_ident().device_name == "LMS10x_FieldEval"
        scan = client.poll()
        ahead = np.abs(scan.angles_rad - np.pi / 2) < np.deg2rad(20)
        a = scan.angles_rad[ahead] - np.pi / 2
        np.testing.assert_allclose(scan.ranges_m[ahead], 3.0 / np.cos(a), atol=0.0005 + 1e-9)
    finally:
        client.close()
    with pytest.raises(SimulatorError):
        _ = server.address
    with pytest.raises(OSError):
        socket.create_connection(address, timeout=2).close()


def test_sim_url_selects_the_lms1xx_sensor() -> None:
    with open_device("scanner", "sim://?scene=wall&realtime=0&sensor=lms1xx&timeout=5") as client:
        assert isinstance(client.sim_server.device.sensor, LMS1xxSensor)
        scan = client.poll()
        ahead = np.abs(scan.angles_rad - np.pi / 2) < np.deg2rad(20)
        a = scan.angles_rad[ahead] - np.pi / 2
        assert np.all(np.abs(scan.ranges_m[ahead] - 3.0 / np.cos(a)) < 0.1)  # 12 mm noise, 8 sigma


def test_dropped_connection_reconnects_and_the_gap_is_counted() -> None:
    with open_device("scanner", "sim://?scene=seed003&realtime=0&timeout=10&backoff=0.05") as client:
        client.start_streaming()
        first = [s.scan_counter for s in client.scans(30)]
        assert np.all(np.diff(first) == 1)
        assert client.sim_server.drop_clients() == 1
        # The queue may still hold scans of the old link: read on until the client has reconnected (keep
        # reading meanwhile, or the fast stream overflows the queue) and 30 scans were read.
        later: list[int] = []
        deadline = time.monotonic() + 30.0  # against a hang, not a timing check
        while len(later) < 30 or not client.connected or client.stats.reconnects < 1:
            assert time.monotonic() < deadline, "the client did not reconnect"
            later.append(client.next_scan().scan_counter)
        client.close()  # its threads end: the stats are final
        while True:  # and the scans still queued belong to the record too
            try:
                later.append(client.next_scan(0.0).scan_counter)
            except ScannerStateError:
                break
        stats = client.stats
        assert stats.reconnects == 1 and stats.connection_losses == 1 and stats.queue_drops == 0
        # Counters only grow; any scans made while the link was down show up as lost, never hidden.
        assert later[0] > first[-1]
        assert stats.lost == sum(np.diff([first[-1], *later]) - 1)


@pytest.mark.parametrize(
    "url",
    [
        "sim://?scene=nope",
        "sim://?cola=c",
        "sim://?scnee=wall",  # unknown options are passed to the tcp client, which rejects them
        "sim://somehost:2112?scene=wall",
        "sim://?realtime=maybe",
        "sim://?sensor=lms2xx",
    ],
)
def test_bad_sim_urls_are_typed_errors(url: str) -> None:
    with pytest.raises(DeviceURLError):
        open_device("scanner", url)
