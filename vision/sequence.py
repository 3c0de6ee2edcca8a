"""A numbered image sequence (``file:views/view-%03d.png``), read file by file.

OpenCV's FFmpeg backend would play it too, but its image2 demuxer scales every image to the
first one's size (a view of another size is then measured, wrongly, instead of rejected as
``wrong_size``) and stops at the first missing number without a word. Read here with
``cv2.imread``, each image keeps its size and every matching file plays, in number order.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from hal.errors import HalConfigError

SEQUENCE = re.compile(r"%(0?\d+)?d")
"""A numbered image sequence, as FFmpeg names it: ``views/view-%03d.png``."""
SEQUENCE_FPS = 25.0
"""The rate a sequence plays at as a live source (FFmpeg's image2 default)."""


def is_sequence(target: str) -> bool:
    return "://" not in target and SEQUENCE.search(target) is not None


def sequence_files(pattern: Path, name: str) -> list[Path]:
    """The files of the sequence ``pattern`` in number order, or one line why there are none:
    the folder is missing, no file matches, the first is numbered above 4 (the rule of
    FFmpeg's sequences, kept so a ``%d`` pattern means the same in both)."""
    folder = pattern.parent
    if not folder.is_dir():
        raise HalConfigError(f"--source {name}: no such folder {folder}")
    at = SEQUENCE.search(pattern.name)
    if at is None:  # the % is in a folder's name
        raise HalConfigError(f"--source {name}: a sequence numbers its files, not its folder")
    head, tail = pattern.name[: at.start()], pattern.name[at.end() :]
    numbers = re.compile(re.escape(head) + r"(\d+)" + re.escape(tail) + "$")
    found = sorted(
        (int(m[1]), p) for p in folder.iterdir() if (m := numbers.match(p.name)) and p.is_file()
    )
    if not found:
        raise HalConfigError(f"--source {name}: no file matches the image sequence")
    if found[0][0] > 4:
        raise HalConfigError(
            f"--source {name}: the images are numbered from {found[0][0]}; an image sequence "
            "starts at 0 to 4 (renumber them, or give a folder to hil camera calibrate --images)"
        )
    return [p for _, p in found]


class SequenceCapture:
    """The part of ``cv2.VideoCapture`` :class:`vision.sources.CaptureSource` uses, over the
    files of a sequence: ``read`` gives each image as 8-bit grey at its own size (None for a
    file OpenCV cannot decode: counted as ``malformed``)."""

    def __init__(self, files: list[Path]) -> None:
        self.files, self.next = files, 0

    def isOpened(self) -> bool:  # VideoCapture's name
        return True

    def get(self, prop: int) -> float:
        return SEQUENCE_FPS if prop == cv2.CAP_PROP_FPS else 0.0

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self.next >= len(self.files):
            return False, None
        path = self.files[self.next]
        self.next += 1
        return True, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)

    def release(self) -> None:
        self.next = len(self.files)
