"""The ``sim://`` device URLs: a simulated device plus the real driver connected to it.

``sim://`` is a first-class device URL (a rig's config swaps ``tcp://10.0.0.5:2112?cola=b`` for
``sim://?cola=b`` and nothing else changes), but it joins two packages that must not know each
other: the simulator (``sim``) and the driver transports (``drivers``). This module is part of the
composition root (``service``), which may use both; importing it registers the handlers with
:mod:`drivers.url`. ``service.cli.main`` and ``service.rig`` import it, and so does the test
suite's root ``conftest.py``.

* scanner ``sim://?cola=b&scene=seed003&realtime=0``: an embedded :class:`~sim.scanner.ScannerServer`
  on 127.0.0.1 and a :class:`drivers.lms100.client.ScannerClient` connected to it over real TCP;
* motor ``sim://?node=1&sync_hz=200``: a :class:`~sim.drive.can_node.SimCanNode` on a private
  python-can ``virtual`` channel and a :class:`drivers.servo.cia402_can.Cia402CanMotor` on it.
"""

from __future__ import annotations

import itertools
from typing import Any
from urllib.parse import urlencode

import can

from drivers import url as device_url
from drivers.errors import DeviceURLError
from drivers.lms100 import client as lms_client
from drivers.servo import cia402_can
from drivers.url import DeviceURL
from lrms.errors import LrmsError
from sim.drive.can_node import SimCanNode
from sim.scanner import ScannerServer, SimulatedLMS100
from sim.scene import SENSOR_NAMES, make_sensor

_SIM_URL_OPTIONS = ("cola", "scene", "realtime", "time_scale", "seed", "sensor")


def open_sim_scanner(url: DeviceURL, **kw: Any) -> Any:
    """``sim://?cola=b&scene=seed003&realtime=0``: an embedded simulated scanner plus a connected client.

    Simulator options: ``cola`` (a|b, default b), ``scene`` (default seed003), ``realtime``
    (default 1), ``time_scale`` (default 1), ``seed`` (default 0), ``sensor`` (ideal|lms1xx,
    default ideal; a ``sensor`` keyword argument wins). Every other option
    (``timeout``, ``reconnect``, ``queue``...) goes to the LMS100 client's ``tcp://`` URL, which
    rejects unknown ones. Keyword arguments ``calibration``, ``motor_angle_at``, ``sensor`` go to
    :class:`SimulatedLMS100`, all others to :func:`drivers.lms100.client.open_url`.

    Returns the :class:`drivers.lms100.client.ScannerClient`, connected over real TCP to a
    :class:`ScannerServer` on 127.0.0.1 (ephemeral port); ``client.sim_server`` is that server and
    ``client.close()`` stops it too.
    """
    if url.host or url.port or url.path not in ("", "/"):
        raise DeviceURLError(f"sim scanner URLs take no host, port or path: {url.raw!r}")
    cola = url.get_str("cola", "b", choices=("a", "b"))
    scene = url.get_str("scene", "seed003")
    realtime = url.get_bool("realtime", True)
    time_scale = url.get_float("time_scale", 1.0, lo=1e-3, hi=1e6)
    seed = url.get_int("seed", 0, lo=0)
    sensor_name = url.get_str("sensor", "ideal", choices=SENSOR_NAMES)
    forward = {k: v for k, v in url.query.items() if k not in _SIM_URL_OPTIONS}
    device_kw = {k: kw.pop(k) for k in ("calibration", "motor_angle_at", "sensor") if k in kw}
    device_kw.setdefault("sensor", make_sensor(sensor_name))
    try:
        device = SimulatedLMS100(scene, seed=seed, realtime=realtime, time_scale=time_scale, **device_kw)
    except LrmsError as exc:  # unknown scene name
        raise DeviceURLError(f"{url.raw!r}: {exc}") from None
    server = ScannerServer(device, dialect=cola).start()
    try:
        host, port = server.address
        query = urlencode({"cola": cola, **forward})
        client = lms_client.open_url(DeviceURL.parse(f"tcp://{host}:{port}?{query}"), **kw)
    except BaseException:
        server.stop()
        raise
    _close_with(client, server)
    return client


def _close_with(client: Any, server: ScannerServer) -> None:
    """Make ``client.close()`` (and so its context manager) also stop the embedded server."""
    original = client.close

    def close() -> None:
        try:
            original()
        finally:
            server.stop()

    client.close = close
    client.sim_server = server


_channel_ids = itertools.count(1)


def open_sim_motor(url: Any, **kwargs: Any) -> Any:
    """``sim://?node=1&sync_hz=100&heartbeat_ms=50``: a simulated drive on a private python-can
    ``virtual`` channel in this process, and the CANopen driver connected to it (returned; its
    ``close()`` also stops the simulated node). Keyword arguments go to the driver
    (``config=DriveConfig(...)``, ``clock=...``); the simulated drive is ``motor.sim_node.drive``.
    """
    parsed = url if isinstance(url, DeviceURL) else DeviceURL.parse(url)
    options = cia402_can.read_url_options(parsed)
    parsed.check_all_used()
    channel = f"lrms-sim-drive-{next(_channel_ids)}-{id(parsed):x}"
    node = SimCanNode(can.Bus(interface="virtual", channel=channel), node_id=options.node).start()

    def stop_node() -> None:
        node.stop()
        node.bus.shutdown()

    try:
        motor = cia402_can.Cia402CanMotor.open_bus(
            {"interface": "virtual", "channel": channel}, options, on_close=stop_node, **kwargs
        )
    except BaseException:
        stop_node()
        raise
    motor.sim_node = node
    return motor


device_url.register("scanner", "sim", open_sim_scanner)
device_url.register("motor", "sim", open_sim_motor)
