"""The raw log: written on its thread, read back, and readable after a crash or a cut."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from service import mcaplog as ml
from tests.conftest import REPO

T0 = 1_763_700_000_000_000_000


def _write(path: Path, n_scans: int = 300, chunk_size: int = 1 << 20) -> None:
    rng = np.random.default_rng(0)
    with ml.McapLog(path, chunk_size=chunk_size) as log:
        log.log_json(ml.TOPIC_MEASUREMENT, T0, {"id": "m1", "request": {"target": "cylinder"}})
        log.log_world_pose(T0, np.eye(4))
        for i in range(n_scans):
            t = T0 + (i + 1) * 20_000_000
            log.log_telegram(t, b"\x02\x02\x02\x02" + i.to_bytes(4, "big") + bytes(8), "b")
            log.log_scan(t + 1, rng.uniform(0.5, 3.0, 541), -np.pi * 0.75, np.pi * 0.75)
            log.log_motor(t + 2, 0.01 * i, 0.17)
            log.log_plane_pose(t + 3, 0.01 * i, 0.1)
        log.log_cloud(T0 + 10**10, rng.normal(size=(1000, 3)))
        log.log_json(ml.TOPIC_RESULT, T0 + 10**10 + 1, {"diameter_m": 0.1375})


def test_written_log_reads_back_with_foxglove_schemas(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write(path, n_scans=50)
    msgs, status = ml.read_log(path)
    assert not status.truncated
    topics = [m.topic for m in msgs]
    assert topics.count(ml.TOPIC_SCAN) == 50 and topics.count(ml.TOPIC_TELEGRAM) == 50
    assert topics.count(ml.TOPIC_TF) == 51 and topics.count(ml.TOPIC_CLOUD) == 1
    scan = next(m for m in msgs if m.topic == ml.TOPIC_SCAN)
    assert scan.schema_name == "foxglove.LaserScan"
    ls = scan.decode()
    assert len(ls.ranges) == 541 and ls.frame_id == "scan_plane"
    cloud = next(m for m in msgs if m.topic == ml.TOPIC_CLOUD).decode()
    assert cloud.point_stride == 12 and len(cloud.data) == 12_000 and [f.name for f in cloud.fields] == list("xyz")
    tel = next(m for m in msgs if m.topic == ml.TOPIC_TELEGRAM)
    assert tel.encoding == "sick-cola-b" and tel.decode()[:4] == b"\x02\x02\x02\x02"
    joint = next(m for m in msgs if m.topic == ml.TOPIC_MOTOR).decode()
    assert joint.joints[0].velocity == pytest.approx(0.17)
    assert next(m for m in msgs if m.topic == ml.TOPIC_RESULT).decode() == {"diameter_m": 0.1375}
    # the standard indexed reader accepts it too (summary written)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(msgs)


def test_quaternion_matches_scipy() -> None:
    from scipy.spatial.transform import Rotation

    rots = [ml.plane_rotation(b) for b in np.linspace(-3.1, 3.1, 41)]
    rots += list(Rotation.random(200, random_state=1).as_matrix())
    for rot in rots:
        q = np.array(ml.quaternion(rot))
        ref = Rotation.from_matrix(rot).as_quat()
        assert np.allclose(q, ref, atol=1e-12) or np.allclose(q, -ref, atol=1e-12)


def test_fast_laserscan_encoding_is_the_protobuf_encoding(tmp_path: Path) -> None:
    from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

    rng = np.random.default_rng(3)
    ranges, inten = rng.uniform(0, 20, 1081), rng.uniform(0, 255, 1081)
    with ml.McapLog(tmp_path / "s.mcap") as log:
        log.log_scan(T0, ranges, -2.0, 2.5, inten)
        log.log_scan(T0 + 1, np.zeros(0), 0.0, 0.0)
    msgs, _ = ml.read_log(tmp_path / "s.mcap")
    ref = LaserScan(
        frame_id="scan_plane", start_angle=-2.0, end_angle=2.5, ranges=ranges.tolist(), intensities=inten.tolist()
    )
    ref.timestamp.seconds, ref.timestamp.nanos = divmod(T0, 1_000_000_000)
    ref.pose.orientation.w = 1.0
    assert msgs[0].data == ref.SerializeToString()
    assert list(msgs[1].decode().ranges) == []


def test_plane_pose_matches_kinematics() -> None:
    from lrms.kinematics import beam_rays

    beta, alpha = 0.7, np.array([-1.0, 0.3, 2.0])
    o, d = beam_rays(alpha, beta, 0.1)
    assert np.allclose(o, [0.1 * np.cos(beta), 0.0, 0.1 * np.sin(beta)])  # the /tf translation
    rot = ml.plane_rotation(beta)
    in_plane = np.stack([np.cos(alpha), np.sin(alpha), np.zeros(3)], axis=-1)  # LaserScan beam directions
    assert np.allclose(in_plane @ rot.T, d)
    assert np.isclose(np.linalg.det(rot), 1.0)


def test_truncated_file_yields_every_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write(path, n_scans=300, chunk_size=32 * 1024)
    full, _ = ml.read_log(path)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) > 5
    data = path.read_bytes()
    for k in (1, len(chunks) // 2, len(chunks) - 1):
        c = chunks[k]
        cut = tmp_path / f"cut{k}.mcap"
        cut.write_bytes(data[: c.chunk_start_offset + c.chunk_length // 2])  # mid-chunk
        got, status = ml.read_log(cut)
        assert status.truncated
        expected = [m for m in full if m.log_time_ns < c.message_start_time]
        assert [(m.topic, m.log_time_ns) for m in got] == [(m.topic, m.log_time_ns) for m in expected]
        assert all(m.decode() is not None for m in got)


def test_json_times_are_foxglove_sec_nsec() -> None:
    t = 1_795_482_796_737_577_436  # > 2**53: a JavaScript number would round it
    assert ml.foxglove_time(t) == {"sec": 1_795_482_796, "nsec": 737_577_436}
    assert ml.time_ns_of(ml.foxglove_time(t)) == t
    assert ml.time_ns_of(t) == t  # the plain integer of logs written before
    with pytest.raises(ml.McapLogError, match="not a logged time"):
        ml.time_ns_of(1.5)


def test_killed_writer_leaves_flushed_chunks_readable(tmp_path: Path) -> None:
    path = tmp_path / "crash.mcap"
    child = textwrap.dedent(
        f"""
        import sys, time
        import numpy as np
        from service import mcaplog as ml
        log = ml.McapLog({str(path)!r}, flush_interval_s=0.05)
        i = 0
        while True:
            log.log_scan(i + 1, np.full(541, 2.0), -2.0, 2.0)
            i += 1
            if log.flushes >= 3:
                print(log.messages_flushed, flush=True)  # this many are in closed chunks
                time.sleep(60)
            time.sleep(0.001)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", child], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    flushed_at_least = int(line)
    msgs, status = ml.read_log(path)
    assert status.truncated  # no summary: the process never finished the file
    assert len(msgs) >= flushed_at_least > 0
    assert [m.log_time_ns for m in msgs] == list(range(1, len(msgs) + 1))


def test_errors(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(ml.McapLogError, match="not an MCAP"):
        ml.read_log(junk)
    with pytest.raises(ml.McapLogError, match="cannot open"):
        ml.read_log(tmp_path / "missing.mcap")
    log = ml.McapLog(tmp_path / "x.mcap")
    with pytest.raises(ml.McapLogError, match="not a JSON topic"):
        log.log_json("/elsewhere", 0, {})
    log.close()
    with pytest.raises(ml.McapLogError, match="closed"):
        log.log_motor(1, 0.0, 0.0)
