"""Camera calibration from views of a ChArUco board (OpenCV): the camera matrix and distortion
the vision pipeline undistorts with (``[vision]`` of the rig config).

A ChArUco board is a checkerboard with an ArUco marker in every white square: each inner corner
is identified by the markers around it, so a view that shows only part of the board still counts,
and the corners reach the image's edges and corners, where the lens distortion is largest. The
corners are refined to sub-pixel accuracy (``cv2.aruco.CharucoDetector``) and
``cv2.calibrateCamera`` fits K and (k1, k2, p1, p2, k3) to all views. Fronto-parallel views
alone cannot separate the focal length from the distance: the board must be seen at tilts (the
real camera's or the emulated one's views, see ``hil camera calibrate``).
"""

from __future__ import annotations

import math
import os
import re
import stat
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from hal.config import RigConfig, config_from_dict, read_text_file
from hal.errors import HalConfigError
from hal.whole_file import written_whole

MIN_CORNERS = 8
"""A view with fewer identified corners is not used (too little of the board in view)."""
MIN_VIEWS = 3
SAME_VIEW_PX = 1.0
"""Two views whose corners all lie within this of each other are one pose seen twice."""
MIN_TILT_DEG = 5.0
"""The board's normal must turn at least this much over the views."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


class CalibrationError(HalConfigError):
    """The views cannot give a calibration (too few usable views, unreadable images)."""


@dataclass(frozen=True)
class CharucoSpec:
    """The printed board: squares across and down, their side and the markers' side (m)."""

    squares_x: int = 14
    squares_y: int = 10
    square_m: float = 0.03
    marker_m: float = 0.0225
    dictionary: int = cv2.aruco.DICT_4X4_100
    cells_per_square: int = 8
    """Resolution of :meth:`cells`: the marker (4x4 bits and a 1-bit border) spans 6 cells."""

    def board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(self.dictionary)
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, d
        )

    def cells(self) -> np.ndarray:
        """The board as reflectances 0..1, one row/column per cell (row 0 at v = 0)."""
        n = self.cells_per_square
        img = self.board().generateImage(
            (self.squares_x * n, self.squares_y * n), marginSize=0, borderBits=1
        )
        return img.astype(np.float64) / 255.0

    @property
    def cell_m(self) -> float:
        return self.square_m / self.cells_per_square

    @property
    def size_m(self) -> tuple[float, float]:
        return (self.squares_x * self.square_m, self.squares_y * self.square_m)


@dataclass(frozen=True)
class Calibration:
    """What ``cv2.calibrateCamera`` found, and from what."""

    width: int
    height: int
    camera_matrix: np.ndarray
    distortion: np.ndarray
    """(k1, k2, p1, p2, k3)."""
    rms_px: float
    """RMS reprojection error over every corner used."""
    views_used: int
    views_total: int
    corners: int

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        return float(self.camera_matrix[1, 2])

    def vision_keys(self) -> dict[str, float | bool]:
        """The ``[vision]`` keys of the rig config."""
        k1, k2, p1, p2, k3 = (float(v) for v in self.distortion[:5])
        return {
            "calibrated": True,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "k1": k1,
            "k2": k2,
            "p1": p1,
            "p2": p2,
            "k3": k3,
        }

    def as_dict(self) -> dict[str, object]:
        return {
            "image_size": [self.width, self.height],
            **{k: v for k, v in self.vision_keys().items() if k != "calibrated"},
            "rms_px": self.rms_px,
            "views_used": self.views_used,
            "views_total": self.views_total,
            "corners": self.corners,
        }


def detect_corners(
    img: np.ndarray, spec: CharucoSpec, detector: cv2.aruco.CharucoDetector | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """The board's identified inner corners in one grey view: (object points (N, 3) m, image
    points (N, 2) px), or None when fewer than :data:`MIN_CORNERS` were found."""
    board = spec.board()
    detector = detector or cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = detector.detectBoard(img)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    obj, pts = board.matchImagePoints(corners, ids)
    return obj.reshape(-1, 3).astype(np.float32), pts.reshape(-1, 2).astype(np.float32)


def calibrate(
    views: Iterable[np.ndarray],
    spec: CharucoSpec | None = None,
    *,
    k3: bool = False,
    tangential: bool = False,
) -> Calibration:
    """Calibrate from grey views (all of one size); :class:`CalibrationError` when fewer than
    :data:`MIN_VIEWS` views show enough of the board.

    By default k3 and the tangential p1, p2 are held at 0 (``k3``, ``tangential`` fit them):
    for a machine-vision lens they are below what 20 views resolve, and a free p1, p2 trades
    against the principal point (measured on the emulated camera: cx off by about 1 px with
    them free, 0.1-0.3 px with them held)."""
    spec = spec or CharucoSpec()
    detector = cv2.aruco.CharucoDetector(spec.board())
    obj_pts: list[np.ndarray] = []
    img_pts: list[np.ndarray] = []
    size: tuple[int, int] | None = None
    total = 0
    for img in views:
        total += 1
        if img.ndim != 2 or img.dtype != np.uint8:
            raise CalibrationError(
                f"view {total}: expected an 8-bit grey image, got {img.dtype} {img.shape}"
            )
        shape = (img.shape[1], img.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise CalibrationError(
                f"view {total} is {shape[0]}x{shape[1]}, the first was {size[0]}x{size[1]}"
            )
        found = detect_corners(img, spec, detector)
        if found is not None:
            obj_pts.append(found[0])
            img_pts.append(found[1])
    found_views = len(obj_pts)
    keep = distinct_views(obj_pts, img_pts)
    if size is not None and found_views >= MIN_VIEWS > len(keep):
        raise CalibrationError(
            f"only {len(keep)} distinct view(s) of {found_views}: the others repeat one (the "
            f"same corners within {SAME_VIEW_PX:g} px); need {MIN_VIEWS} or more board poses"
        )
    obj_pts, img_pts = [obj_pts[i] for i in keep], [img_pts[i] for i in keep]
    if size is None or len(obj_pts) < MIN_VIEWS:
        raise CalibrationError(
            f"only {len(obj_pts)} of {total} view(s) show at least {MIN_CORNERS} board corners; "
            f"need {MIN_VIEWS} or more (is the board {spec.squares_x}x{spec.squares_y} squares, "
            "DICT_4X4_100?)"
        )
    flags = (0 if k3 else cv2.CALIB_FIX_K3) | (0 if tangential else cv2.CALIB_ZERO_TANGENT_DIST)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, k, dist, rvecs, _ = cv2.calibrateCamera(
        obj_pts, img_pts, size, None, None, flags=flags, criteria=crit
    )
    tilt = tilt_spread_deg(rvecs)
    if tilt < MIN_TILT_DEG:
        raise CalibrationError(
            f"the {len(obj_pts)} views show the board at one orientation (its normal within "
            f"{tilt:.1f} deg, under {MIN_TILT_DEG:g}): the focal length is not determined; "
            "tilt the board between views"
        )
    return Calibration(
        size[0],
        size[1],
        k,
        np.asarray(dist, dtype=np.float64).reshape(-1)[:5],
        float(rms),
        len(obj_pts),
        total,
        int(sum(len(p) for p in img_pts)),
    )


def distinct_views(obj_pts: list[np.ndarray], img_pts: list[np.ndarray]) -> list[int]:
    """The views that do not repeat an earlier one (the same corners, each within
    :data:`SAME_VIEW_PX`): a repeated pose adds no constraint, only a false confidence."""
    keep: list[int] = []
    for i, (obj, img) in enumerate(zip(obj_pts, img_pts, strict=True)):
        if not any(
            obj.shape == obj_pts[j].shape
            and np.array_equal(obj, obj_pts[j])
            and float(np.abs(img - img_pts[j]).max()) < SAME_VIEW_PX
            for j in keep
        ):
            keep.append(i)
    return keep


def tilt_spread_deg(rvecs: Iterable[np.ndarray]) -> float:
    """The largest angle between the board's normals over the views, in degrees (a planar
    target seen at one orientation leaves the focal length undetermined: Zhang, 2000)."""
    normals = [cv2.Rodrigues(np.asarray(r, dtype=np.float64))[0][:, 2] for r in rvecs]
    cos = min((abs(float(a @ b)) for a in normals for b in normals), default=1.0)
    return math.degrees(math.acos(min(1.0, cos)))


def read_images(folder: str | Path) -> list[np.ndarray]:
    """Every image file of ``folder`` (sorted by name) as 8-bit grey."""
    root = Path(folder)
    if not root.is_dir():
        raise CalibrationError(f"--images {root}: not a folder")
    files = sorted(  # hidden files are no views (a Mac's ._view.png beside view.png)
        p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.name[0] != "."
    )
    if not files:
        raise CalibrationError(f"--images {root}: no image files ({', '.join(IMAGE_SUFFIXES)})")
    out = []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"{p}: not an image OpenCV can read")
        if out and img.shape != out[0].shape:  # named by file: "view 2" is no file name
            (h, w), (h0, w0) = img.shape, out[0].shape
            raise CalibrationError(
                f"{p} is {w}x{h}, {files[0]} is {w0}x{h0}: every view must be of one camera"
            )
        out.append(img)
    return out


_SECTION = re.compile(r"^\s*\[\s*vision\s*\]\s*(#.*)?$")
_ANY_SECTION = re.compile(r"^\s*\[")


def write_vision_section(path: str | Path, calibration: Calibration) -> RigConfig:
    """Write the calibration into the rig config ``path`` (TOML): the calibration keys of its
    ``[vision]`` section are replaced (the section moves to the end; its heading comment, its
    other keys and every other section stay as they were), or the section is appended. The
    file is created when missing; the result is validated like any config before it replaces
    the file."""
    p = Path(path)
    mode = check_writable(p)
    try:  # a folder, a FIFO, a PNG or a log named by mistake: one line
        text = read_text_file(p, "config file") if p.exists() or p.is_symlink() else ""
    except HalConfigError as exc:
        raise HalConfigError(f"{exc}, not touched") from None
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise HalConfigError(f"{p}: not valid TOML, not touched: {exc}") from None
    c = calibration
    values = c.vision_keys()
    kept: list[str] = []
    heading: list[str] = []  # the section's comment lines above its first key stay on top
    others: list[str] = []
    notes: dict[str, str] = {}
    inside = keyed = False
    for line in text.splitlines():
        if _SECTION.match(line):
            inside = True
            continue
        if inside and _ANY_SECTION.match(line):
            inside = False
        if not inside:
            kept.append(line)
        elif not keyed and line.lstrip().startswith("#"):
            heading.append(line)
        elif line.strip():
            keyed = True
            name, _, value = line.partition("=")
            if name.strip() not in values:
                others.append(line)  # the section's other keys stay
            elif "#" in value:  # a number or a bool, then the key's own comment: kept
                notes[name.strip()] = "  #" + value.split("#", 1)[1].rstrip()
    while kept and not kept[-1].strip():
        kept.pop()
    block = [
        f"[vision]            # hil camera calibrate: {c.views_used} of {c.views_total} views, "
        f"{c.corners} corners, RMS {c.rms_px:.3f} px, {c.width}x{c.height}",
        *heading,
        *(
            f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v)}{notes.get(k, '')}"
            for k, v in values.items()
        ),
        *others,
    ]
    new_text = "\n".join([*kept, *([""] if kept else []), *block]) + "\n"
    cfg = config_from_dict(tomllib.loads(new_text), source=str(p))  # validated before writing
    with written_whole(p) as tmp:
        tmp.write_text(new_text, encoding="utf-8")
        if mode is not None:  # the new file replaces the old one: keep its permissions
            tmp.chmod(mode)
    return cfg


def check_writable(path: str | Path) -> int | None:
    """The permission bits of the rig config ``path`` (None: it does not exist yet), or one
    line when it is read-only: the file is replaced by a rename, which its own mode does not
    stop, so ``chmod a-w`` ("do not touch") is honoured here (also for root)."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return None  # missing (created), or said by the read that follows
    if stat.S_ISREG(st.st_mode) and (not st.st_mode & 0o222 or not os.access(p, os.W_OK)):
        raise HalConfigError(
            f"{p}: read-only, not touched (make it writable, or give --write FILE)"
        )
    return stat.S_IMODE(st.st_mode)
