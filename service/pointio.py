"""Reading point clouds: ``.xyz`` / ``.txt`` / ``.csv`` (x y z, extra columns ignored) and ``.ply``.

Text files: one point per line, separated by whitespace, commas or semicolons; blank lines and
lines starting with ``#`` or ``//`` are skipped, and so is a single header line of names
(``x,y,z,...``). Units are metres. PLY (ASCII or binary): the ``vertex`` element's ``x``, ``y``,
``z`` properties, read with ``plyfile`` except an ASCII file whose first element is a vertex block
of scalar properties, which numpy parses. Anything else is a :class:`PointFileError`.

Text is parsed by :func:`numpy.loadtxt` (C) after commas and semicolons become spaces; a file it
refuses goes through the line-by-line reader, which names the first bad line. 100k points: about
4 times faster than the line-by-line reader alone, and ASCII PLY about 4 times faster than
``plyfile`` (``bench/bench_cli_start.py``).
"""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from service.errors import ServiceError

TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts", ".asc")
_SPLIT = re.compile(r"[,;\s]+")


class PointFileError(ServiceError):
    """A point file is missing, of an unknown kind, or malformed."""


def read_points(path: str | Path) -> NDArray[np.float64]:
    """The cloud in ``path`` as an ``(N, 3)`` float array (metres)."""
    p = Path(path)
    if not p.is_file():
        raise PointFileError(f"{p}: no such file")
    suffix = p.suffix.lower()
    if suffix == ".ply":
        pts = _read_ply(p)
    elif suffix in TEXT_SUFFIXES:
        pts = _read_text(p)
    else:
        raise PointFileError(f"{p}: unknown point file type {suffix!r} (use .xyz, .txt, .csv or .ply)")
    if pts.shape[0] == 0:
        raise PointFileError(f"{p}: no points")
    if not np.all(np.isfinite(pts)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(pts), axis=1)))
        raise PointFileError(f"{p}: {bad} point(s) with non-finite coordinates")
    return pts


def _read_text(p: Path) -> NDArray[np.float64]:
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise PointFileError(f"{p}: not a text file ({exc.reason})") from exc
    fast = _parse_text_fast(text)
    return fast if fast is not None else _parse_text_lines(p, text)


_TO_SPACE = str.maketrans(",;", "  ")


def _parse_text_fast(text: str) -> NDArray[np.float64] | None:
    """The whole text at once by :func:`numpy.loadtxt`, or ``None`` when it cannot be read that way
    (the caller's line-by-line reader then says where and why)."""
    clean = text.translate(_TO_SPACE)
    # a header line of names: the first line that is neither blank nor a comment, if its first
    # three fields are not numbers
    skip = 0
    for i, raw in enumerate(io.StringIO(clean)):
        line = raw.strip()
        if not line or line.startswith(("#", "//")):
            continue
        fields = line.split()
        try:
            [float(f) for f in fields[:3]]
        except ValueError:
            if len(fields) >= 3:  # a shorter line is an error the line reader reports
                skip = i + 1
        break
    # looking for comments costs loadtxt a third of its time: only when there can be any
    comments = ("#", "//") if "#" in clean or "//" in clean else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "input contained no data": no points, said below
        try:
            pts = np.loadtxt(io.StringIO(clean), comments=comments, usecols=(0, 1, 2), skiprows=skip, ndmin=2)
        except (ValueError, IndexError):
            return None
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def _parse_text_lines(p: Path, text: str) -> NDArray[np.float64]:
    rows: list[list[float]] = []
    header_allowed = True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith(("#", "//")):
            continue
        fields = [f for f in _SPLIT.split(line) if f]
        if len(fields) < 3:
            raise PointFileError(f"{p}:{lineno}: need at least 3 columns (x y z), got {len(fields)}")
        try:
            rows.append([float(fields[0]), float(fields[1]), float(fields[2])])
        except ValueError:
            if header_allowed and not rows:
                header_allowed = False
                continue
            raise PointFileError(f"{p}:{lineno}: not a number in {line[:60]!r}") from None
        header_allowed = False
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def _read_ply(p: Path) -> NDArray[np.float64]:
    fast = _read_ascii_ply_fast(p)
    if fast is not None:
        return fast
    from plyfile import PlyData, PlyParseError

    try:
        ply = PlyData.read(str(p))
    except (PlyParseError, ValueError, EOFError, OSError, IndexError) as exc:
        raise PointFileError(f"{p}: not a readable PLY file ({exc})") from exc
    if "vertex" not in ply:
        raise PointFileError(f"{p}: PLY file has no 'vertex' element")
    vertex = ply["vertex"]
    names = {prop.name for prop in vertex.properties}
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise PointFileError(f"{p}: PLY vertices lack {', '.join(missing)}")
    return np.column_stack([np.asarray(vertex[c], dtype=np.float64) for c in ("x", "y", "z")])


def _read_ascii_ply_fast(p: Path) -> NDArray[np.float64] | None:
    """An ASCII PLY whose first element is ``vertex`` with scalar properties only (the common
    point cloud), by :func:`numpy.loadtxt` on its vertex lines; ``None`` for anything else (binary,
    lists in the vertex, odd headers), which :mod:`plyfile` reads (20 times slower on ASCII)."""
    with p.open("rb") as fh:
        if fh.readline().strip() != b"ply":
            return None
        names: list[str] = []
        count = -1
        ascii_format = False
        header_lines = 1
        words: list[str] = []
        for raw in fh:
            header_lines += 1
            words = raw.decode("ascii", errors="replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format":
                ascii_format = words[1:2] == ["ascii"]
            elif words[0] == "element":
                if count >= 0 or len(words) != 3 or words[1] != "vertex":
                    break  # the vertex block is not first: leave it to plyfile
                count = int(words[2]) if words[2].isdigit() else -1
                if count < 0:
                    return None
            elif words[0] == "property" and count >= 0:
                if len(words) != 3:
                    return None  # a list property
                names.append(words[2])
            elif words[0] == "end_header":
                break
            if header_lines > 200:
                return None
        if not ascii_format or count < 0 or words[:1] != ["end_header"]:
            return None
        if not all(c in names for c in ("x", "y", "z")):
            return None
        cols = tuple(names.index(c) for c in ("x", "y", "z"))
        body = fh.read().decode("ascii", errors="replace")
    try:
        pts = np.loadtxt(io.StringIO(body), usecols=cols, max_rows=count, ndmin=2, comments=None)
    except (ValueError, IndexError):
        return None
    if pts.shape[0] != count:
        return None
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def write_xyz(path: str | Path, points: NDArray[np.float64]) -> None:
    """Write ``(N, 3)`` points as text, one ``x y z`` line each (metres, 0.1 um resolution)."""
    np.savetxt(str(path), np.asarray(points, dtype=np.float64).reshape(-1, 3), fmt="%.7f")
