"""The target the camera looks at: what is printed on the plane z = z_wo, in one place.

Both sides read it: the emulated camera draws it (``plant_emulator.camera_sensor``) and the
vision pipeline knows what to look for (it never imports the emulator; on a real rig this is the
marker you print). The target point of eq. (6) is the disc's centre.

Why a disc and not an ArUco/AprilTag marker: on the emulated camera (640x480, the paper's lens)
the grey-weighted centroid of a dark disc measured its centre to well under 0.05 px with no
noise, against several times that for the mean of an ArUco marker's four ``cornerSubPix``
corners (figures in the commit that chose it); a disc is rotation-invariant, has no corners to
lose in motion blur, and the centroid of a disc blurred by linear motion is the disc at the
middle of the exposure, which is exactly the frame's capture stamp.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TargetMarker:
    """A dark disc printed on bright paper."""

    shape: str = "disc"
    diameter_m: float = 0.03
    """Disc diameter on the plane, m (41 px across at the paper's s·λ / z_wo = 1367 px/m)."""
    ink: float = 0.15
    """Reflectance of the disc, 0..1 (the image's grey level is reflectance times 255)."""
    paper: float = 0.8
    """Reflectance of the plane around it, 0..1."""


TARGET_MARKER = TargetMarker()
"""The rig's target marker."""
