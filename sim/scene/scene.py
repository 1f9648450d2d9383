"""A scene: named shapes with remission, ray-cast all at once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sim.scene.shapes import FloatArray, SceneError, Shape, check_rays


@dataclass(frozen=True)
class SceneObject:
    """One shape of a scene with its diffuse remission (0..1, 1 = white paper) and a name."""

    shape: Shape
    remission: float
    name: str


@dataclass(frozen=True)
class Hits:
    """Result of :meth:`Scene.raycast` for ``N`` rays.

    ``range``: distance to the first hit (m), inf for a miss; ``index``: index of the object hit
    in :attr:`Scene.objects` (-1: miss); ``cos_incidence``: ``|cos|`` of the angle between ray
    and surface normal (0 for a miss); ``remission``: the object's remission (0 for a miss);
    ``normal``: outward unit normal at the hit (nan for a miss).
    """

    range: FloatArray
    index: NDArray[np.intp]
    cos_incidence: FloatArray
    remission: FloatArray
    normal: FloatArray

    @property
    def hit(self) -> NDArray[np.bool_]:
        return self.index >= 0

    def points(self, origins: ArrayLike, dirs: ArrayLike) -> FloatArray:
        """Hit points ``(N, 3)`` (nan for misses)."""
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        t = np.where(self.hit, self.range, np.nan)
        return np.asarray(o + t[:, None] * d, dtype=np.float64)


class Scene:
    """A list of shapes. ``raycast`` returns the first hit of every ray, exactly, vectorized."""

    def __init__(self, name: str = "scene") -> None:
        self.name = name
        self.objects: list[SceneObject] = []

    def add(self, shape: Shape, remission: float = 0.5, name: str | None = None) -> int:
        """Add ``shape``; returns its index (the ``Hits.index`` of rays that hit it)."""
        if not isinstance(shape, Shape):
            raise SceneError(f"not a shape: {shape!r}")
        rem = float(remission)
        if not np.isfinite(rem) or not 0.0 <= rem <= 10.0:
            raise SceneError(f"remission must be within 0..10 (1 = white diffuse), got {remission!r}")
        label = name if name is not None else f"{type(shape).__name__.lower()}{len(self.objects)}"
        if any(o.name == label for o in self.objects):
            raise SceneError(f"scene {self.name!r} already has an object named {label!r}")
        self.objects.append(SceneObject(shape, rem, label))
        return len(self.objects) - 1

    def index_of(self, name: str) -> int:
        for i, obj in enumerate(self.objects):
            if obj.name == name:
                return i
        raise SceneError(f"scene {self.name!r} has no object named {name!r}")

    def __len__(self) -> int:
        return len(self.objects)

    def raycast(self, origins: ArrayLike, dirs: ArrayLike) -> Hits:
        """First hit of each ray: origins ``(N, 3)``, unit directions ``(N, 3)``."""
        o, d = check_rays(origins, dirs)
        count = len(o)
        best_t = np.full(count, np.inf)
        best_i = np.full(count, -1, dtype=np.intp)
        best_n = np.full((count, 3), np.nan)
        for i, obj in enumerate(self.objects):
            center, radius = obj.shape.bounding_sphere()
            if np.isfinite(radius):
                # Cull with the bounding sphere: only rays that pass within it are tested exactly.
                oc = center - o
                along = np.einsum("ij,ij->i", oc, d)
                dist2 = np.einsum("ij,ij->i", oc, oc) - along**2
                far_end = along + radius
                sel = np.flatnonzero((dist2 <= radius * radius * (1 + 1e-9) + 1e-12) & (far_end > 0))
                if sel.size == 0:
                    continue
                t, n = obj.shape.intersect(o[sel], d[sel])
                better = t < best_t[sel]
                idx = sel[better]
            else:
                t, n = obj.shape.intersect(o, d)
                better = t < best_t
                idx = np.flatnonzero(better)
            best_t[idx] = t[better]
            best_i[idx] = i
            best_n[idx] = n[better]
        hit = best_i >= 0
        cos_inc = np.where(hit, np.abs(np.einsum("ij,ij->i", np.nan_to_num(best_n), d)), 0.0)
        rem_table = np.array([obj.remission for obj in self.objects] + [0.0])
        remission = rem_table[best_i]  # index -1 picks the trailing 0
        return Hits(range=best_t, index=best_i, cos_incidence=cos_inc, remission=remission, normal=best_n)
