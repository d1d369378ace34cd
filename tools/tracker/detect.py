"""Markers in a camera frame -> their poses on the arena's floor.

OpenCV's ArUco detector finds each marker's four corners, refined by fitting lines to its
edges (CORNER_REFINE_CONTOUR: on rendered frames a tenth of the heading error that sub-pixel
corner refinement left). Each corner is undistorted and its ray from the camera intersected
with the markers' plane (``camera_pose`` in the calibration), or mapped by the plane's
homography (``floor_homography``). The marker's centre is the mean of its four corners on the
plane; its heading is the direction from its bottom edge to its top edge (the mean of its four
edges' directions, each turned to point up). A module carries its marker with the top edge
towards its front connector, so the heading is the module's. The fit error is how far the four
sides and two diagonals measured on the plane are from a square of ``marker_mm`` (RMS): a wrong
height, a bent module or a misread marker shows there. Detections further off than a quarter
of the marker's side are dropped (counted as rejected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from dh2rt.errors import OptionError
from dh2rt.wire.tracker import MarkerPose
from tools.tracker.calibration import Calibration

Points = npt.NDArray[np.float64]
#: The dictionaries ``--dictionary`` accepts: OpenCV's predefined ArUco and AprilTag ones.
DICTIONARIES = tuple(name for name in dir(cv2.aruco) if name.startswith("DICT_"))
DEFAULT_DICTIONARY = "DICT_4X4_50"
#: A detection whose fit error exceeds this share of the marker's side is dropped.
MAX_FIT_ERROR = 0.25


def aruco_dictionary(name: str) -> Any:
    """OpenCV's predefined dictionary ``name`` (``DICT_4X4_50``, ...); OptionError otherwise."""
    if name not in DICTIONARIES:
        raise OptionError(f"--dictionary {name!r}: not one of OpenCV's ({', '.join(DICTIONARIES)})")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@dataclass
class Detections:
    """One frame's markers, and how many detections were dropped (a bad fit, an id seen twice)."""

    poses: list[MarkerPose] = field(default_factory=list)
    rejected: int = 0


class MarkerDetector:
    """Finds the markers of one dictionary in frames of one calibrated camera."""

    def __init__(self, calibration: Calibration, marker_mm: float, dictionary: str = DEFAULT_DICTIONARY) -> None:
        if not math.isfinite(marker_mm) or marker_mm <= 0:
            raise OptionError(f"--marker-mm {marker_mm!r}: expected a size in millimetres, more than 0")
        self.calibration = calibration
        self.marker_mm = marker_mm
        parameters = cv2.aruco.DetectorParameters()
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
        smallest = self.smallest_perimeter_rate()
        if smallest is not None:  # OpenCV's default (0.03 of the frame's side) misses small markers on wide frames
            parameters.minMarkerPerimeterRate = min(parameters.minMarkerPerimeterRate, smallest)
        self._detector = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), parameters)
        # a true square's four sides and two diagonals, as _pose measures them
        self._square = np.array([marker_mm] * 4 + [marker_mm * math.sqrt(2)] * 2, dtype=np.float64)

    def smallest_perimeter_rate(self) -> float | None:
        """Half the perimeter a marker on the plane under the camera spans, as a share of the
        frame's longer side (ArUco's ``minMarkerPerimeterRate``): no smaller candidate can be
        one of ours. None where the calibration gives no distance (a homography)."""
        cal = self.calibration
        if cal.translation_mm is None or cal.image_size is None:
            return None
        distance = float(cal.translation_mm[2]) - cal.marker_height_mm
        if distance <= 0:
            return None
        side_px = cal.fx * self.marker_mm / distance
        return 0.5 * 4 * side_px / max(cal.image_size)

    def detect(self, image: npt.NDArray[Any]) -> Detections:
        """The markers in ``image`` (BGR or grey), by ascending id."""
        size = self.calibration.image_size
        if size is not None and (image.shape[1], image.shape[0]) != size:
            raise OptionError(
                f"a frame of {image.shape[1]}x{image.shape[0]} pixels; the calibration is for {size[0]}x{size[1]}"
            )
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self._detector.detectMarkers(grey)
        found = Detections()
        if ids is None:
            return found
        by_marker: dict[int, list[MarkerPose | None]] = {}
        for marker_corners, marker_id in zip(corners, ids.reshape(-1), strict=True):
            marker = int(marker_id)
            pixels = np.asarray(marker_corners, dtype=np.float64).reshape(4, 2)
            by_marker.setdefault(marker, []).append(self._pose(marker, pixels))
        for marker in sorted(by_marker):
            poses = by_marker[marker]
            pose = poses[0]
            if len(poses) > 1 or pose is None:  # one id twice in a frame: neither can be trusted
                found.rejected += len(poses)
                continue
            found.poses.append(pose)
        return found

    def on_plane(self, pixels: Points) -> Points:
        """Pixels (n x 2) -> arena points (n x 2, mm) on the markers' plane."""
        cal = self.calibration
        raw = pixels.reshape(-1, 1, 2)
        if cal.homography is not None:
            undistorted = cv2.undistortPoints(raw, cal.camera_matrix, cal.distortion_vector, P=cal.camera_matrix)
            mapped = cv2.perspectiveTransform(undistorted, cal.homography)
            return np.asarray(mapped, dtype=np.float64).reshape(-1, 2)
        assert cal.rotation is not None and cal.translation_mm is not None
        normalised = np.asarray(cv2.undistortPoints(raw, cal.camera_matrix, cal.distortion_vector)).reshape(-1, 2)
        rays = np.column_stack([normalised, np.ones(len(normalised))]) @ cal.rotation.T
        with np.errstate(divide="ignore", invalid="ignore"):
            reach = (cal.marker_height_mm - cal.translation_mm[2]) / rays[:, 2]
        reach[~(reach > 0)] = np.nan  # a ray that never meets the plane in front of the camera
        return np.asarray(cal.translation_mm[:2] + rays[:, :2] * reach[:, None], dtype=np.float64)

    def _pose(self, marker: int, pixels: Points) -> MarkerPose | None:
        # ArUco's corners: the marker's top-left, top-right, bottom-right, bottom-left
        c = self.on_plane(pixels)
        if not np.all(np.isfinite(c)):
            return None
        measured = np.array(
            [np.linalg.norm(c[k] - c[(k + 1) % 4]) for k in range(4)]
            + [np.linalg.norm(c[0] - c[2]), np.linalg.norm(c[1] - c[3])]
        )
        error = float(np.sqrt(np.mean((measured - self._square) ** 2)))
        if error > MAX_FIT_ERROR * self.marker_mm:
            return None
        centre = c.mean(axis=0)
        up = (c[0] - c[3]) + (c[1] - c[2])  # the left and right edges, bottom to top
        right = (c[1] - c[0]) + (c[2] - c[3])  # the top and bottom edges, left to right
        up = up + np.array([-right[1], right[0]])  # all four edges: half the corners' noise
        heading = math.degrees(math.atan2(up[1], up[0])) % 360.0
        return MarkerPose(marker, float(centre[0]), float(centre[1]), heading, error)
