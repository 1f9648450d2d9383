"""Point files: text (xyz/txt/csv) and PLY through plyfile, with clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from service.pointio import PointFileError, read_points, write_xyz

PTS = np.array([[0.1, 2.5, 0.3], [0.2, 2.4, -0.1], [1e-3, 3.0, 1.25]])


def test_xyz_round_trip_and_extra_columns(tmp_path: Path) -> None:
    f = tmp_path / "a.xyz"
    write_xyz(f, PTS)
    np.testing.assert_allclose(read_points(f), PTS, atol=1e-7)
    g = tmp_path / "b.txt"
    g.write_text("# scan 1\n\nx y z intensity\n" + "\n".join(f"{a} {b} {c} 17 99" for a, b, c in PTS) + "\n")
    np.testing.assert_allclose(read_points(g), PTS)


def test_csv_with_header_and_semicolons(tmp_path: Path) -> None:
    f = tmp_path / "a.csv"
    f.write_text("x,y,z,rssi\n" + "\n".join(f"{a},{b},{c},5" for a, b, c in PTS))
    np.testing.assert_allclose(read_points(f), PTS)
    g = tmp_path / "b.csv"
    g.write_text("\n".join(f"{a};{b};{c}" for a, b, c in PTS))
    np.testing.assert_allclose(read_points(g), PTS)


@pytest.mark.parametrize("text", [False, True])
def test_ply_binary_and_ascii(tmp_path: Path, text: bool) -> None:
    v = np.array([(*p, 7) for p in PTS], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u1")])
    f = tmp_path / "a.ply"
    PlyData([PlyElement.describe(v, "vertex")], text=text).write(str(f))
    np.testing.assert_allclose(read_points(f), PTS, rtol=1e-6)


def test_errors_are_typed_and_clear(tmp_path: Path) -> None:
    with pytest.raises(PointFileError, match="no such file"):
        read_points(tmp_path / "missing.xyz")
    (tmp_path / "a.las").write_text("1 2 3\n")
    with pytest.raises(PointFileError, match="unknown point file type"):
        read_points(tmp_path / "a.las")
    (tmp_path / "two.xyz").write_text("1 2\n3 4\n")
    with pytest.raises(PointFileError, match="at least 3 columns"):
        read_points(tmp_path / "two.xyz")
    (tmp_path / "bad.xyz").write_text("1 2 3\n4 five 6\n")
    with pytest.raises(PointFileError, match=r"bad.xyz:2: not a number"):
        read_points(tmp_path / "bad.xyz")
    (tmp_path / "empty.csv").write_text("# nothing\n")
    with pytest.raises(PointFileError, match="no points"):
        read_points(tmp_path / "empty.csv")
    (tmp_path / "nan.xyz").write_text("1 2 3\nnan 1 1\n")
    with pytest.raises(PointFileError, match="non-finite"):
        read_points(tmp_path / "nan.xyz")
    (tmp_path / "junk.ply").write_bytes(b"not a ply file at all")
    with pytest.raises(PointFileError, match="PLY"):
        read_points(tmp_path / "junk.ply")
    face = np.array([(1, 2, 3)], dtype=[("a", "i4"), ("b", "i4"), ("c", "i4")])
    PlyData([PlyElement.describe(face, "vertex")]).write(str(tmp_path / "noxyz.ply"))
    with pytest.raises(PointFileError, match="lack x, y, z"):
        read_points(tmp_path / "noxyz.ply")


def test_fast_text_reader_agrees_with_the_line_reader(tmp_path: Path) -> None:
    """The whole-file parse (numpy.loadtxt) and the line-by-line reader give the same points on
    every text layout the reader accepts: separators mixed, comments anywhere, a header, extra
    columns, blank lines and CRLF line ends."""
    from service.pointio import _parse_text_fast, _parse_text_lines

    pts = np.round(np.random.default_rng(3).uniform(-5, 5, (500, 3)), 9)
    lines = [f"{a:.9f},{b:.9f};{c:.9f} 0.5" for a, b, c in pts]
    lines[10:10] = ["# a comment", "", "// another"]
    text = "X;Y;Z;I\r\n" + "\r\n".join(lines) + "\r\n"
    fast = _parse_text_fast(text)
    assert fast is not None
    np.testing.assert_array_equal(fast, _parse_text_lines(tmp_path / "t.csv", text))
    np.testing.assert_array_equal(fast, pts)
    f = tmp_path / "t.csv"
    f.write_text(text)
    np.testing.assert_array_equal(read_points(f), pts)
    # what the fast parse refuses goes to the line reader, which names the line
    assert _parse_text_fast("1 2 3\n4 5\n") is None
    assert _parse_text_fast("x y\n1 2 3\n") is None  # a header needs three names too
    (tmp_path / "short.xyz").write_text("1 2 3\n4 5\n")
    with pytest.raises(PointFileError, match=r"short.xyz:2: need at least 3 columns"):
        read_points(tmp_path / "short.xyz")


def test_ascii_ply_with_faces_after_the_vertices(tmp_path: Path) -> None:
    """The fast ASCII PLY path reads only the vertex block (a face list may follow); a vertex with a
    list property is left to plyfile, and both agree with plyfile's own reading."""
    v = np.array([(*p, 7) for p in PTS], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("i", "u1")])
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    f = tmp_path / "mesh.ply"
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(faces, "face")], text=True).write(str(f))
    np.testing.assert_allclose(read_points(f), PTS, rtol=1e-12)
    vl = np.empty(3, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("n", object)])
    vl["x"], vl["y"], vl["z"] = PTS.T
    vl["n"] = [np.array([1, 2], dtype=np.int32)] * 3
    g = tmp_path / "listy.ply"
    PlyData([PlyElement.describe(vl, "vertex")], text=True).write(str(g))
    np.testing.assert_allclose(read_points(g), PTS, rtol=1e-12)
