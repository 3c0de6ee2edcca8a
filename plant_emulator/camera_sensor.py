"""The emulated camera sensor: renders 8-bit grey frames of the plane z = z_wo from the camera pose.

Geometry (the paper's camera, eq. 6, is the special case of no distortion and fx = fy = s·λ):
the camera looks along Z_w at the plane z = z_wo; its frame is OpenCV's (X_c right, Y_c down
the image, Z_c forward) turned by the heading phi about Z_w, so a plane point p seen from a
camera at p_c has normalised coordinates ``x_n = R(phi)^T (p - p_c) / z_wo`` and, through a
true lens on OpenCV's distortion model (k1, k2, p1, p2, k3), lands at pixel
``(u, v) = (cx + fx x_d, cy + fy y_d)`` with ``x_d = distort(x_n)``. The ideal features of
eq. (6) are ``f = s·λ · x_n``: pixels about the principal point, undistorted, on the image axes.

Rendering is by inverse mapping: every pixel centre is undistorted once per lens (the rays are
precomputed), and per frame only the ray-plane intersection (a similarity transform, since the
plane is parallel to the image) and the texture lookup remain. Sub-pixel accuracy comes from area
averaging: a texture integrates itself over each pixel's footprint on the plane (a box filter,
analytic for the disc and for cell grids), which is what supersampling approximates, at one
sample per pixel. Only the part of the frame the texture's support covers is computed; the rest
is the plain background.

Motion blur: the frame is the mean of sub-exposure renders spread over the exposure; their number
follows the image motion over the exposure (a sub-exposure per 0.25 px of motion, 1 when still,
at most :data:`MAX_SUBEXPOSURES`). Sensor: grey level = reflectance x 255 DN, shot noise of
variance ``DN / electrons_per_dn`` plus read noise (near-Gaussian draws, see
:func:`plant_emulator.camera_exposure.expose`), rounded and clipped to uint8. The noise of frame
``k`` is a function of ``(seed, k)`` and the pixel alone, so a frame is the same whatever came
before it, on any machine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from plant_emulator import camera_exposure as kernels
from plant_emulator.camera import CameraPose
from plant_emulator.camera_lens import Intrinsics, LensDistortion, distort, undistort
from plant_emulator.camera_textures import DiscTexture, PlaneTexture
from plant_emulator.errors import CameraSensorError

FULL_SCALE_DN = 255.0
MAX_SUBEXPOSURES = 32
SUBEXPOSURE_PX = 0.25
"""Image motion per sub-exposure, px (a blur sampled finer than a quarter pixel)."""
_ROI_PAD_PX = 3
_U64 = (1 << 64) - 1


@dataclass(frozen=True)
class Resolution:
    width: int
    height: int


@dataclass(frozen=True)
class SensorNoise:
    """Shot noise (variance DN / electrons_per_dn; 0 = off) and read noise (std, DN; 0 = off)."""

    electrons_per_dn: float = 0.0
    read_noise_dn: float = 0.0

    @property
    def off(self) -> bool:
        return self.electrons_per_dn <= 0.0 and self.read_noise_dn <= 0.0


@dataclass(frozen=True)
class Placement:
    """Where a planar texture lies in the world (m): its origin and two orthonormal in-plane
    axes; texture coordinates (u, v) are along them. The target plane z = z_wo is
    ``Placement((0, 0, z_wo), (1, 0, 0), (0, 1, 0))``."""

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray


Scene = Callable[[float], PlaneTexture]
"""The plane's texture at a time (s): the target jump moves the marker in the world."""


class CameraSensor:
    """Renders what the camera sees: :meth:`render` a frame, :meth:`project` a world point."""

    def __init__(
        self,
        intrinsics: Intrinsics,
        distortion: LensDistortion,
        resolution: Resolution,
        noise: SensorNoise,
        exposure_s: float,
        seed: int,
        *,
        z_wo: float,
        scene: Scene,
    ) -> None:
        if resolution.width <= 0 or resolution.height <= 0:
            raise CameraSensorError(f"resolution must be positive, got {resolution}")
        if not exposure_s >= 0:
            raise CameraSensorError(f"exposure must be non-negative, got {exposure_s}")
        if not z_wo > 0:
            raise CameraSensorError(f"the plane's depth z_wo must be positive, got {z_wo}")
        self.intrinsics = intrinsics
        self.distortion = distortion
        self.resolution = resolution
        self.noise = noise
        self.exposure_s = float(exposure_s)
        self.seed = int(seed)
        self.z_wo = float(z_wo)
        self.scene = scene
        self._rays_x, self._rays_y, self._footprint = _pixel_rays(
            intrinsics, distortion, resolution
        )
        k = intrinsics
        corners = np.array([[0, 0], [resolution.width, resolution.height]], dtype=float)
        self._max_radius_px = float(np.max(np.hypot(corners[:, 0] - k.cx, corners[:, 1] - k.cy)))
        self._blank: tuple[tuple[int, int, float], np.ndarray] | None = None
        self._outlines: dict[tuple[float, float, float, float], tuple[np.ndarray, np.ndarray]] = {}

    @property
    def shape(self) -> tuple[int, int]:
        return (self.resolution.height, self.resolution.width)

    def project(self, pose: CameraPose, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` (u, v) of world points on the plane, through the lens."""
        c, s = math.cos(pose.phi), math.sin(pose.phi)
        u, v = self._pixels(
            pose.x, pose.y, c, s, np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        )
        return np.stack([u, v], axis=-1)

    def _pixels(self, px, py, c, s, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project` for a camera at ``(px, py)`` turned by ``(c, s) = (cos, sin)`` of its
        heading: scalars, or columns for one pose a row of ``x`` and ``y``."""
        dx, dy = x - px, y - py
        xn, yn = (c * dx + s * dy) / self.z_wo, (-s * dx + c * dy) / self.z_wo
        xd, yd = distort(xn, yn, self.distortion)
        k = self.intrinsics
        return k.cx + k.fx * xd, k.cy + k.fy * yd

    def subexposures(self, pose_at: Callable[[float], CameraPose], t_mid: float) -> np.ndarray:
        """Times (s) of the sub-exposures of a frame exposed around ``t_mid``."""
        e = self.exposure_s
        if e <= 0:
            return np.array([t_mid])
        a, b = pose_at(t_mid - e / 2), pose_at(t_mid + e / 2)
        gain = max(self.intrinsics.fx, self.intrinsics.fy) / self.z_wo
        dphi = abs(math.remainder(b.phi - a.phi, 2 * math.pi))
        motion = gain * math.hypot(b.x - a.x, b.y - a.y) + dphi * self._max_radius_px
        n = min(MAX_SUBEXPOSURES, max(1, math.ceil(motion / SUBEXPOSURE_PX)))
        return t_mid + e * ((np.arange(n) + 0.5) / n - 0.5)

    def exposed_region(
        self, pose_at: Callable[[float], CameraPose], t_mid: float
    ) -> tuple[float, tuple[slice, slice] | None, np.ndarray | None]:
        """What the exposure around ``t_mid`` sees: the plane's background reflectance, and the
        region of the frame the texture's support covers with its reflectance (float, 0..1,
        averaged over the exposure; None, None: the texture is out of view)."""
        times = [float(t) for t in self.subexposures(pose_at, t_mid)]
        poses = [pose_at(t) for t in times]
        textures = [self.scene(t) for t in times]
        background = float(textures[0].background)
        # one region for the whole exposure: the union of the first and last sub-exposure's
        # (a still exposure has one: its region once, not twice)
        ends = [(poses[0], textures[0])]
        if len(times) > 1:
            ends.append((poses[-1], textures[-1]))
        rois = self._rois(ends)
        if not rois:
            return background, None, None
        roi = tuple(
            slice(min(r[a].start for r in rois), max(r[a].stop for r in rois)) for a in (0, 1)
        )
        if all(t == textures[0] for t in textures[1:]):  # one texture: all sub-exposures at once
            if isinstance(textures[0], DiscTexture):
                return background, roi, self._disc_mean(poses, textures[0], roi)
            return background, roi, self._sample_many(poses, textures[0], roi).mean(axis=0)
        acc = np.zeros((roi[0].stop - roi[0].start, roi[1].stop - roi[1].start))
        for pose, texture in zip(poses, textures, strict=True):
            acc += self._sample(pose, texture, roi)
        return background, roi, acc / len(times)

    def irradiance(self, pose_at: Callable[[float], CameraPose], t_mid: float) -> np.ndarray:
        """Noise-free reflectance image (float, 0..1) averaged over the exposure."""
        background, roi, values = self.exposed_region(pose_at, t_mid)
        out = np.full(self.shape, background)
        if roi is not None:
            out[roi] = values
        return out

    def render(
        self, pose_at: Callable[[float], CameraPose], t_mid: float, *, frame: int = 0
    ) -> np.ndarray:
        """One 8-bit grey frame exposed around ``t_mid`` (s); ``frame`` keys its noise.

        The same pixels as :meth:`expose` of :meth:`irradiance`: the background with the
        frame's noise (made ahead by :meth:`prepare`, else now), then the region the target
        covers exposed over it (the noise is per pixel, so the order does not matter)."""
        background, roi, values = self.exposed_region(pose_at, t_mid)
        key = (self.seed, int(frame), background)
        ready, self._blank = self._blank, None
        if ready is not None and ready[0] == key:
            out = ready[1]
        else:
            out = self._expose_flat(background, frame)
        if roi is not None:
            self._expose_into(out, roi, values, frame)
        return out

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel a frame may need: a first frame
        with the target in view would otherwise be late by the JIT time (about a second)."""
        tiny, one = np.zeros((2, 2)), np.zeros(1)
        ones = tiny + 1.0
        kernels.disc_mean(tiny, tiny, ones, one, one, one + 1.0, one, 0.0, 0.0, 1.0, 0.0, 1.0, tiny)
        self._expose_into(np.zeros(self.shape, np.uint8), (slice(0, 2), slice(0, 2)), tiny, 0)
        self.render_window(lambda t: CameraPose(0.0, 0.0, 0.0), 0.0, (0, 0, 2, 2))
        self.expose(tiny, 0)  # also the plain plane's (a one-element reflectance)

    def prepare(self, frame: int, background: float) -> None:
        """Make ahead the part of frame ``frame`` that no pose changes (the plane's
        ``background`` reflectance with the frame's noise), so :meth:`render` only exposes the
        target's region: a camera renders the next frame's background while it waits for the
        pose. Kept for one :meth:`render` of that frame (same seed, same background)."""
        blank = self._expose_flat(background, frame)
        self._blank = ((self.seed, int(frame), float(background)), blank)

    def _expose_flat(self, background: float, frame: int) -> np.ndarray:
        """:meth:`expose` of the plain plane (``background`` everywhere), the same pixels."""
        out = np.empty(self.shape, dtype=np.uint8)
        kernels.expose(np.full(1, float(background)), out.ravel(), *self._noise_args(frame))
        return out

    def _noise_args(self, frame: int) -> tuple[float, float, float, np.uint64, np.uint64]:
        n = self.noise
        return (
            FULL_SCALE_DN,
            1.0 / n.electrons_per_dn if n.electrons_per_dn > 0 else 0.0,
            n.read_noise_dn**2,
            np.uint64(self.seed & _U64),
            np.uint64(int(frame) & _U64),
        )

    def expose(self, reflectance: np.ndarray, frame: int) -> np.ndarray:
        """The sensor: a reflectance image (0..1) to 8-bit grey levels with frame ``frame``'s
        shot and read noise (a function of the seed, the frame and the pixel alone)."""
        dn = np.ascontiguousarray(reflectance, dtype=np.float64)
        out = np.empty(dn.shape, dtype=np.uint8)
        kernels.expose(dn.ravel(), out.ravel(), *self._noise_args(frame))
        return out

    def _expose_into(
        self, out: np.ndarray, roi: tuple[slice, slice], values: np.ndarray, frame: int
    ) -> None:
        """Expose the region ``roi`` of ``out`` (a whole frame) from its reflectance ``values``,
        each pixel with the noise of its place in the whole frame."""
        rows, cols = roi
        kernels.expose_window(
            np.ascontiguousarray(values, dtype=np.float64),
            out[roi],
            rows.start,
            cols.start,
            self.resolution.width,
            *self._noise_args(frame),
        )

    def render_window(
        self,
        pose_at: Callable[[float], CameraPose],
        t_mid: float,
        window: tuple[int, int, int, int],
        *,
        frame: int = 0,
    ) -> np.ndarray:
        """The region ``window = (x0, y0, x1, y1)`` (px, end exclusive, inside the frame) of
        :meth:`render`'s frame, the same pixels (noise keyed by the pixel's place in the whole
        frame), rendered and exposed there only: a camera's region-of-interest readout."""
        x0, y0, x1, y1 = window
        h, w = self.shape
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise CameraSensorError(f"window {window} is not inside the {w}x{h} frame")
        background, roi, values = self.exposed_region(pose_at, t_mid)
        out = np.empty((y1 - y0, x1 - x0), dtype=np.uint8)
        noise = self._noise_args(frame)
        kernels.expose_window(np.full((1, 1), float(background)), out, y0, x0, w, *noise)
        if roi is not None:
            rs, cs = roi
            r0, r1 = max(rs.start, y0), min(rs.stop, y1)
            c0, c1 = max(cs.start, x0), min(cs.stop, x1)
            if r0 < r1 and c0 < c1:
                part = values[r0 - rs.start : r1 - rs.start, c0 - cs.start : c1 - cs.start]
                kernels.expose_window(
                    np.ascontiguousarray(part, dtype=np.float64),
                    out[r0 - y0 : r1 - y0, c0 - x0 : c1 - x0],
                    r0,
                    c0,
                    w,
                    *noise,
                )
        return out

    def render_view(
        self, pose: CameraPose, placement: Placement, texture: PlaneTexture, *, frame: int = 0
    ) -> np.ndarray:
        """One still frame of a planar ``texture`` placed anywhere in front of the camera
        (a calibration board held at a tilt), with the sensor's noise; outside the texture's
        plane or behind the camera is the texture's background."""
        c, s = math.cos(pose.phi), math.sin(pose.phi)
        rx, ry = self._rays_x, self._rays_y
        d = np.stack([c * rx - s * ry, s * rx + c * ry, np.ones_like(rx)])
        normal = np.cross(placement.axis_u, placement.axis_v)
        rel = placement.origin - np.array([pose.x, pose.y, 0.0])
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = float(normal @ rel) / np.tensordot(normal, d, axes=1)
        hit = np.isfinite(lam) & (lam > 0)
        pts = lam * d - rel[:, None, None]
        u = np.tensordot(placement.axis_u, pts, axes=1)
        v = np.tensordot(placement.axis_v, pts, axes=1)
        du_r, du_c = np.gradient(u)
        dv_r, dv_c = np.gradient(v)
        side = np.sqrt(np.abs(du_c * dv_r - du_r * dv_c))
        ok = hit & np.isfinite(side)
        refl = np.full(self.shape, float(texture.background))
        refl[ok] = texture.sample(u[ok], v[ok], side[ok])
        return self.expose(refl, frame)

    def _rois(self, ends: list[tuple[CameraPose, PlaneTexture]]) -> list[tuple[slice, slice]]:
        """The frame regions the textures' supports cover from each pose, padded (those in
        view): the support's outline, 9 points a side, through the lens, all poses in one
        vectorised pass (the exposure's first and last sub-exposure)."""
        h, w = self.shape
        whole = (slice(0, h), slice(0, w))
        outlines = [self._outline(tex.support()) for _, tex in ends]
        if any(o is None for o in outlines):
            return [whole]
        bx = np.stack([o[0] for o in outlines])  # type: ignore[index]
        by = np.stack([o[1] for o in outlines])  # type: ignore[index]
        u, v = self._pixels(
            np.array([[p.x] for p, _ in ends]),
            np.array([[p.y] for p, _ in ends]),
            np.array([[math.cos(p.phi)] for p, _ in ends]),
            np.array([[math.sin(p.phi)] for p, _ in ends]),
            bx,
            by,
        )
        lo_u = np.floor(u.min(axis=1)) - _ROI_PAD_PX
        lo_v = np.floor(v.min(axis=1)) - _ROI_PAD_PX
        hi_u = np.ceil(u.max(axis=1)) + _ROI_PAD_PX + 1
        hi_v = np.ceil(v.max(axis=1)) + _ROI_PAD_PX + 1
        out = []
        for i in range(len(ends)):
            u0, v0 = max(int(lo_u[i]), 0), max(int(lo_v[i]), 0)
            u1, v1 = min(int(hi_u[i]), w), min(int(hi_v[i]), h)
            if u0 < u1 and v0 < v1:
                out.append((slice(v0, v1), slice(u0, u1)))
        return out

    def _outline(
        self, box: tuple[float, float, float, float] | None
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """A support box's outline, 9 points a side (cached: a scene has a box or two)."""
        if box is None:
            return None
        hit = self._outlines.get(box)
        if hit is None:
            x0, y0, x1, y1 = box
            s = np.linspace(0.0, 1.0, 9)
            bx = np.concatenate(
                [x0 + (x1 - x0) * s, np.full(9, x1), x1 - (x1 - x0) * s, np.full(9, x0)]
            )
            by = np.concatenate(
                [np.full(9, y0), y0 + (y1 - y0) * s, np.full(9, y1), y1 - (y1 - y0) * s]
            )
            if len(self._outlines) >= 64:
                self._outlines.clear()
            hit = self._outlines[box] = (bx, by)
        return hit

    def _sample_many(
        self, poses: list[CameraPose], texture: PlaneTexture, roi: tuple[slice, slice]
    ) -> np.ndarray:
        """:meth:`_sample` for several poses in one vectorised pass: (len(poses), h, w)."""
        phi = np.array([p.phi for p in poses])[:, None, None]
        px = np.array([p.x for p in poses])[:, None, None]
        py = np.array([p.y for p in poses])[:, None, None]
        c, s = np.cos(phi), np.sin(phi)
        rx, ry = self._rays_x[roi] * self.z_wo, self._rays_y[roi] * self.z_wo
        out = texture.sample(
            px + c * rx - s * ry, py + s * rx + c * ry, self._footprint[roi] * self.z_wo
        )
        return np.where(np.isfinite(out), out, 0.0)

    def _disc_mean(
        self, poses: list[CameraPose], disc: DiscTexture, roi: tuple[slice, slice]
    ) -> np.ndarray:
        """``_sample_many(poses, disc, roi).mean(axis=0)`` in one compiled pass, without the
        (len(poses), h, w) intermediates (the same reflectance to 1e-15: a square root and a
        reciprocal where numpy takes ``hypot`` and divides). Measured (640x480, a blurred
        frame of 24-32 sub-exposures, busy 2-core host, medians of 200): 1.2-2.6 ms with
        numpy, 0.30-0.38 ms compiled."""
        phi = np.array([p.phi for p in poses])
        px = np.array([p.x for p in poses])
        py = np.array([p.y for p in poses])
        rx, ry = self._rays_x[roi] * self.z_wo, self._rays_y[roi] * self.z_wo
        out = np.empty(rx.shape)
        kernels.disc_mean(
            rx,
            ry,
            self._footprint[roi] * self.z_wo,
            px,
            py,
            np.cos(phi),
            np.sin(phi),
            disc.cx,
            disc.cy,
            disc.radius,
            disc.ink,
            disc.background,
            out,
        )
        return out

    def _sample(
        self, pose: CameraPose, texture: PlaneTexture, roi: tuple[slice, slice]
    ) -> np.ndarray:
        c, s = math.cos(pose.phi), math.sin(pose.phi)
        rx, ry = self._rays_x[roi] * self.z_wo, self._rays_y[roi] * self.z_wo
        x = pose.x + c * rx - s * ry
        y = pose.y + s * rx + c * ry
        out = texture.sample(x, y, self._footprint[roi] * self.z_wo)
        return np.where(np.isfinite(out), out, 0.0)


def _pixel_rays(
    k: Intrinsics, d: LensDistortion, res: Resolution
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates of every pixel centre and each pixel's footprint side
    (sqrt of its area on the z = 1 plane)."""
    u = np.arange(res.width, dtype=float)
    v = np.arange(res.height, dtype=float)
    uu, vv = np.meshgrid(u, v)
    xn, yn, ok = undistort((uu - k.cx) / k.fx, (vv - k.cy) / k.fy, d)
    if not np.all(ok):
        raise CameraSensorError(
            f"the lens {d} cannot be inverted at {np.count_nonzero(~ok)} pixel(s) of "
            f"{res.width}x{res.height}: reduce the distortion"
        )
    if d.none:
        side = np.full(xn.shape, math.sqrt(1.0 / (k.fx * k.fy)))
    else:
        dxu, dxv = np.gradient(xn, axis=1), np.gradient(xn, axis=0)
        dyu, dyv = np.gradient(yn, axis=1), np.gradient(yn, axis=0)
        side = np.sqrt(np.abs(dxu * dyv - dxv * dyu))
    return xn, yn, side
