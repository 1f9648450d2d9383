"""Reading point clouds: ``.xyz`` / ``.txt`` / ``.csv`` (x y z, extra columns ignored) and ``.ply``.

Text files: one point per line, separated by whitespace, commas or semicolons; blank lines and
lines starting with ``#`` or ``//`` are skipped, and so is a single header line of names
(``x,y,z,...``). Units are metres. PLY (ASCII or binary) is read with ``plyfile``: the
``vertex`` element's ``x``, ``y``, ``z`` properties. Anything else is a :class:`PointFileError`.
"""

from __future__ import annotations

import re
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
    rows: list[list[float]] = []
    header_allowed = True
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise PointFileError(f"{p}: not a text file ({exc.reason})") from exc
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


def write_xyz(path: str | Path, points: NDArray[np.float64]) -> None:
    """Write ``(N, 3)`` points as text, one ``x y z`` line each (metres, 0.1 um resolution)."""
    np.savetxt(str(path), np.asarray(points, dtype=np.float64).reshape(-1, 3), fmt="%.7f")
