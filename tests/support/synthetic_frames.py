"""Frames of a dark disc on a lighter textured plane, drawn with OpenCV for the vision tests
(independent of the emulator's renderer): an ideal pinhole image, 16x supersampled, then
optionally warped through a true lens, blurred along a motion and given noise."""

from __future__ import annotations

import cv2
import numpy as np

from vision.intrinsics import Intrinsics

SUPERSAMPLE = 16


def ideal_disc(
    k: Intrinsics, f: tuple[float, float], radius_px: float = 12.0, *, texture: bool = True
) -> np.ndarray:
    """Float image (0..255) of the disc centred at features ``f`` in the ideal image."""
    s = SUPERSAMPLE
    u, v = k.cx + f[0], k.cy + f[1]
    img = np.full((k.height, k.width), 200.0)
    if texture:
        yy, xx = np.mgrid[0 : k.height, 0 : k.width]
        img += 20.0 * np.sin(xx / 23.0) * np.cos(yy / 31.0)
    # Coverage of each pixel by the disc, from a supersampled window around it.
    r = int(radius_px) + 3
    x0, y0 = int(np.floor(u)) - r, int(np.floor(v)) - r
    win = np.zeros(((2 * r + 1) * s, (2 * r + 1) * s), np.uint8)
    centre = (round((u - x0 + 0.5) * s * 256 - 128), round((v - y0 + 0.5) * s * 256 - 128))
    cv2.circle(win, centre, round(radius_px * s * 256), 255, -1, cv2.LINE_8, shift=8)
    cover = win.reshape(2 * r + 1, s, 2 * r + 1, s).mean(axis=(1, 3)) / 255.0
    ys, xs = (
        slice(max(y0, 0), min(y0 + 2 * r + 1, k.height)),
        slice(max(x0, 0), min(x0 + 2 * r + 1, k.width)),
    )
    if ys.stop <= ys.start or xs.stop <= xs.start:
        return img  # the disc lies outside the image
    c = cover[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0]
    img[ys, xs] = img[ys, xs] * (1 - c) + 40.0 * c
    return img


def through_lens(k: Intrinsics, ideal: np.ndarray) -> np.ndarray:
    """The image the distorted lens of ``k`` makes of an ideal image."""
    if not k.distorted:
        return ideal
    yy, xx = np.mgrid[0 : k.height, 0 : k.width].astype(np.float64)
    pts = np.stack([xx.ravel(), yy.ravel()], axis=1).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(pts, k.matrix, k.distortion).reshape(k.height, k.width, 2)
    mx = (norm[..., 0] * k.fx + k.cx).astype(np.float32)
    my = (norm[..., 1] * k.fy + k.cy).astype(np.float32)
    return cv2.remap(ideal.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderValue=200.0)


def frame(
    k: Intrinsics,
    f: tuple[float, float],
    *,
    radius_px: float = 12.0,
    noise: float = 0.0,
    blur_px: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """An 8-bit grey frame of the disc at ``f``: lens, then motion blur of ``blur_px`` along u,
    then Gaussian noise of std ``noise`` grey levels."""
    img = through_lens(k, ideal_disc(k, f, radius_px)).astype(np.float64)
    if blur_px > 0:
        n = max(round(blur_px), 1)
        kernel = np.ones((1, n)) / n
        img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def write_image_log(
    path, images: list[np.ndarray], *, chunk_size: int | None = None, tail: bytes | None = None
):
    """An MCAP log of ``images`` as PNG ``foxglove.CompressedImage`` on /camera/image, 0.1 s
    apart (``chunk_size`` 1: each in its own chunk); ``tail``: one more message of these raw
    bytes (a damaged frame) after them. Returns ``path``."""
    from foxglove.messages import CompressedImage, Timestamp
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh) if chunk_size is None else Writer(fh, chunk_size=chunk_size)
        w.start()
        sid = w.register_schema(
            "foxglove.CompressedImage", "protobuf", CompressedImage.get_schema().data
        )
        ch = w.register_channel("/camera/image", "protobuf", sid)
        for i, img in enumerate(images):
            png = cv2.imencode(".png", img)[1].tobytes()
            msg = CompressedImage(timestamp=Timestamp(sec=i), frame_id="c", data=png, format="png")
            w.add_message(ch, i * 10**8, msg.encode(), i * 10**8)
        if tail is not None:
            t = len(images) * 10**8
            w.add_message(ch, t, tail, t)
        w.finish()
    return path
