"""The overhead camera's calibration file (``dh2rt tracker --calibration FILE``), JSON::

    {
      "fx": 1319.1, "fy": 1319.1, "cx": 640.0, "cy": 480.0,   intrinsics, pixels
      "distortion": [k1, k2, p1, p2, k3],                      OpenCV's order; [] for none
      "image_size": [1280, 960],                               optional: frames must match
      "marker_height_mm": 27.4,                                the markers' plane over the floor
      and exactly one of
      "camera_pose": {"rotation": [[...], [...], [...]],       camera frame -> arena frame
                      "translation_mm": [x, y, z]},            the camera's centre in the arena
      "floor_homography": [[...], [...], [...]]                undistorted pixel -> arena mm,
                                                               on the markers' plane
    }

The camera frame is OpenCV's (x right, y down, z out of the lens); the arena frame has z up,
its floor at z = 0. OpenCV's ``calibrateCamera`` gives the intrinsics and distortion;
``solvePnP`` on four or more floor points of known arena position gives the camera pose (invert
it: ``rotation = R.T``, ``translation_mm = -R.T @ t``); or ``findHomography`` from their
undistorted pixels to their arena positions gives the homography. ``sim.overhead`` writes this
file for its rendered frames. A bad file is an :class:`~dh2rt.errors.OptionError` naming the
file and the field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dh2rt.errors import OptionError

Matrix = npt.NDArray[np.float64]
#: The fields a file may have.
FIELDS = {"fx", "fy", "cx", "cy", "distortion", "image_size", "marker_height_mm", "camera_pose", "floor_homography"}
#: The lengths OpenCV accepts for a distortion vector.
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


@dataclass(frozen=True)
class Calibration:
    """A camera over the arena: intrinsics, distortion, and where the markers' plane lies."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()
    image_size: tuple[int, int] | None = None
    marker_height_mm: float = 0.0
    rotation: Matrix | None = None  # camera -> arena
    translation_mm: Matrix | None = None  # the camera's centre in the arena
    homography: Matrix | None = None  # undistorted pixel -> arena mm

    @property
    def camera_matrix(self) -> Matrix:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion_vector(self) -> Matrix:
        return np.array(self.distortion, dtype=np.float64)

    def to_json(self) -> dict[str, Any]:
        """The file's content (see the module docs)."""
        found: dict[str, Any] = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}
        found["distortion"] = list(self.distortion)
        if self.image_size is not None:
            found["image_size"] = list(self.image_size)
        found["marker_height_mm"] = self.marker_height_mm
        if self.rotation is not None and self.translation_mm is not None:
            found["camera_pose"] = {"rotation": self.rotation.tolist(), "translation_mm": self.translation_mm.tolist()}
        if self.homography is not None:
            found["floor_homography"] = self.homography.tolist()
        return found

    def write(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n", encoding="utf-8")


class _Fields:
    """Reads one file's fields, each refusal naming the file and the field."""

    def __init__(self, path: Path, data: dict[str, Any]) -> None:
        self.path, self.data = path, data

    def fail(self, field: str, message: str) -> OptionError:
        return OptionError(f"--calibration {self.path}: field {field!r}: {message}")

    def number(self, field: str, value: Any = None, *, positive: bool = False) -> float:
        value = self.data.get(field) if value is None else value
        if value is None:
            raise self.fail(field, "missing")
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise self.fail(field, f"expected a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(field, f"expected a number more than 0, got {value!r}")
        return float(value)

    def numbers(self, field: str, value: Any, length: int | tuple[int, ...]) -> list[float]:
        lengths = (length,) if isinstance(length, int) else length
        if not isinstance(value, list) or len(value) not in lengths:
            raise self.fail(field, f"expected a list of {' or '.join(map(str, lengths))} numbers, got {value!r}")
        return [self.number(f"{field}[{k}]", v) for k, v in enumerate(value)]

    def matrix(self, field: str, value: Any) -> Matrix:
        if not isinstance(value, list) or len(value) != 3:
            raise self.fail(field, f"expected 3 rows of 3 numbers, got {value!r}")
        return np.array([self.numbers(f"{field}[{k}]", row, 3) for k, row in enumerate(value)])


def load_calibration(path: Path) -> Calibration:
    """Read a calibration file; OptionError (exit 2) naming the file and the field otherwise."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise OptionError(f"--calibration {path}: cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise OptionError(f"--calibration {path}: not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise OptionError(f"--calibration {path}: expected a JSON object, got {type(data).__name__}")
    fields = _Fields(path, data)
    unknown = sorted(set(data) - FIELDS)
    if unknown:
        raise fields.fail(unknown[0], "unknown field")
    fx, fy = fields.number("fx", positive=True), fields.number("fy", positive=True)
    cx, cy = fields.number("cx"), fields.number("cy")
    distortion = tuple(fields.numbers("distortion", data.get("distortion", []), DISTORTION_LENGTHS))
    size = data.get("image_size")
    image_size = None
    if size is not None:
        if not isinstance(size, list) or len(size) != 2 or not all(type(v) is int and v > 0 for v in size):
            raise fields.fail("image_size", f"expected [width, height] in pixels, got {size!r}")
        image_size = (size[0], size[1])
    height = fields.number("marker_height_mm", data.get("marker_height_mm", 0.0))
    pose, homography = data.get("camera_pose"), data.get("floor_homography")
    if (pose is None) == (homography is None):
        raise fields.fail("camera_pose", "give exactly one of camera_pose and floor_homography")
    intrinsics = Calibration(fx, fy, cx, cy, distortion, image_size, height)
    if homography is not None:
        h = fields.matrix("floor_homography", homography)
        if abs(np.linalg.det(h)) < 1e-12:
            raise fields.fail("floor_homography", "the matrix is singular")
        return replace(intrinsics, homography=h)
    if not isinstance(pose, dict) or set(pose) != {"rotation", "translation_mm"}:
        raise fields.fail("camera_pose", f"expected rotation and translation_mm, got {pose!r}")
    rotation = fields.matrix("camera_pose.rotation", pose["rotation"])
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise fields.fail("camera_pose.rotation", "not a rotation matrix (orthonormal, determinant 1)")
    translation = np.array(fields.numbers("camera_pose.translation_mm", pose["translation_mm"], 3))
    if translation[2] <= height:
        raise fields.fail("camera_pose.translation_mm", f"the camera ({translation[2]:g} mm) is not above the markers")
    return replace(intrinsics, rotation=rotation, translation_mm=translation)
