"""Where ``dh2rt tracker`` gets frames: a camera or a video through OpenCV's ``VideoCapture``, or
a folder of images read in name order (a replay, or frames ``sim.overhead`` rendered).

Each frame carries its capture time, microseconds since the Unix epoch: when a camera's or a
video's frame was grabbed, when an image was read. An image that does not decode is a frame
with no image (counted, skipped); a camera or video that ends or fails ends the source.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from dh2rt.closing import Closing
from dh2rt.errors import OptionError

#: The images a folder's frames may be.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class Frame:
    image: npt.NDArray[np.uint8] | None  # None: the image did not decode
    captured_us: int


def _now_us() -> int:
    return time.time_ns() // 1000


class FrameSource(Closing):
    """Frames, in order, until the source ends."""

    name: str

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def close(self) -> None:
        """Nothing to let go of unless a device is open."""


class FolderSource(FrameSource):
    """The images of a folder, by name."""

    def __init__(self, folder: Path) -> None:
        if not folder.is_dir():
            raise OptionError(f"--frames {folder}: not a folder")
        self.name = str(folder)
        self.paths = sorted(path for path in folder.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES)
        if not self.paths:
            raise OptionError(f"--frames {folder}: no images in it ({' '.join(IMAGE_SUFFIXES)})")

    def __iter__(self) -> Iterator[Frame]:
        for path in self.paths:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            yield Frame(None if image is None else np.asarray(image, dtype=np.uint8), _now_us())


class CaptureSource(FrameSource):
    """A camera (by index) or a video file, through ``cv2.VideoCapture``."""

    def __init__(self, device: int | Path, option: str) -> None:
        self.name = f"camera {device}" if isinstance(device, int) else str(device)
        if isinstance(device, Path) and not device.is_file():
            raise OptionError(f"{option} {device}: no such file")
        self.capture: Any = cv2.VideoCapture(device) if isinstance(device, int) else cv2.VideoCapture(str(device))
        if not self.capture.isOpened():
            self.capture.release()
            raise OptionError(f"{option} {device}: OpenCV cannot open it")

    def __iter__(self) -> Iterator[Frame]:
        while True:
            ok, image = self.capture.read()
            captured = _now_us()
            if not ok or image is None:
                return
            yield Frame(np.asarray(image, dtype=np.uint8), captured)

    def close(self) -> None:
        self.capture.release()


def open_source(ns: argparse.Namespace) -> FrameSource:
    """The source the options name (exactly one of --camera, --video, --frames)."""
    if ns.frames is not None:
        return FolderSource(ns.frames)
    if ns.video is not None:
        return CaptureSource(ns.video, "--video")
    return CaptureSource(int(ns.camera), "--camera")
