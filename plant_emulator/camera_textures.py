"""What is printed on the plane z = z_wo, as the emulated camera samples it: the target marker
(a disc) and cell grids (checkerboard, ArUco, ChArUco boards for calibration), each area-averaged
over a pixel's footprint so that rendering at one sample per pixel keeps sub-pixel accuracy
(:mod:`plant_emulator.camera_sensor`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from hal.target_marker import TARGET_MARKER, TargetMarker
from plant_emulator.errors import CameraSensorError


@runtime_checkable
class PlaneTexture(Protocol):
    """What is printed on the plane z = z_wo, in world coordinates (m)."""

    background: float
    """Reflectance (0..1) everywhere outside :meth:`support`."""

    def support(self) -> tuple[float, float, float, float] | None:
        """World box ``(x0, y0, x1, y1)`` outside which the texture is ``background``; None:
        anywhere."""
        ...

    def sample(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Reflectance at world points ``(x, y)`` averaged over a pixel's footprint (side
        ``footprint``, m), 0..1."""
        ...


@dataclass(frozen=True)
class DiscTexture:
    """A disc of reflectance ``ink`` on ``background``; area-averaged by the signed distance to
    its rim (a pixel half inside is half ink), which keeps the centroid unbiased."""

    cx: float
    cy: float
    radius: float
    ink: float
    background: float

    def support(self) -> tuple[float, float, float, float]:
        r = self.radius
        return (self.cx - r, self.cy - r, self.cx + r, self.cy + r)

    def sample(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        inside = np.clip(0.5 - (np.hypot(x - self.cx, y - self.cy) - self.radius) / footprint, 0, 1)
        return self.background + (self.ink - self.background) * inside


def marker_texture(center: np.ndarray, marker: TargetMarker = TARGET_MARKER) -> DiscTexture:
    """The rig's target marker (:mod:`hal.target_marker`) centred at ``center`` (m)."""
    if marker.shape != "disc":
        raise CameraSensorError(f"target marker shape {marker.shape!r} cannot be drawn")
    return DiscTexture(
        float(center[0]), float(center[1]), marker.diameter_m / 2, marker.ink, marker.paper
    )


@dataclass(frozen=True)
class GridTexture:
    """A grid of cells of reflectance ``cells[i, j]`` (row i along +y, column j along +x) of
    side ``cell_m`` from ``origin``: a checkerboard, an ArUco marker or a ChArUco board. Box
    filtered exactly (the footprint as an axis-aligned square no larger than a cell)."""

    cells: np.ndarray
    origin: tuple[float, float]
    cell_m: float
    background: float

    def support(self) -> tuple[float, float, float, float]:
        rows, cols = self.cells.shape
        x0, y0 = self.origin
        return (x0, y0, x0 + cols * self.cell_m, y0 + rows * self.cell_m)

    def sample(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        rows, cols = self.cells.shape
        padded = np.pad(np.asarray(self.cells, dtype=float), 1, constant_values=self.background)
        w = np.minimum(footprint / self.cell_m, 1.0)
        out = np.zeros(np.broadcast(x, y).shape)
        u = (x - self.origin[0]) / self.cell_m
        v = (y - self.origin[1]) / self.cell_m
        j0, wx0 = _box_split(u, w)
        i0, wy0 = _box_split(v, w)
        for di, wy in ((0, wy0), (1, 1.0 - wy0)):
            ii = np.clip(i0 + di + 1, 0, rows + 1)
            for dj, wx in ((0, wx0), (1, 1.0 - wx0)):
                jj = np.clip(j0 + dj + 1, 0, cols + 1)
                out += wy * wx * padded[ii, jj]
        return out


def _box_split(u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell index of a box [u - w/2, u + w/2)'s left end and the fraction of the box in it."""
    left = u - w / 2
    i0 = np.floor(left)
    frac = np.clip((i0 + 1.0 - left) / w, 0.0, 1.0)
    return i0.astype(np.intp), frac
