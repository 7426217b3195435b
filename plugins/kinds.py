"""The contract of each backend kind: the method a backend implements and what it returns.

Shapes use (row, col) for images and (x, y) pixel coordinates for points, with
the centre of pixel (row i, col j) at (x=j, y=i) as in OpenCV and dlib.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import Backend


@dataclass(frozen=True)
class Landmarks:
    """The subject's face in one image.

    points : ndarray, shape (68, 2), float64 — iBUG 68 landmarks (x, y)
    box : ndarray, shape (4,), float64 — face box (left, top, right, bottom)
    n_faces : int — faces found in the image (the subject is one of them)
    """

    points: np.ndarray
    box: np.ndarray
    n_faces: int


@dataclass(frozen=True)
class Pose:
    """Head pose: canonical template point X maps to camera point ``R(rvec) X + tvec``.

    rvec, tvec : ndarray, shape (3,) — OpenCV Rodrigues rotation and translation
    camera : ndarray, shape (3, 3) — intrinsics K
    rms : float — reprojection error of the landmarks, pixels
    """

    rvec: np.ndarray
    tvec: np.ndarray
    camera: np.ndarray
    rms: float

    def as_vector(self) -> np.ndarray:
        """(rx, ry, rz, tx, ty, tz, f, cx, cy, rms) as float64, the store's row."""
        k = self.camera
        return np.r_[self.rvec, self.tvec, k[0, 0], k[0, 2], k[1, 2], self.rms].astype(np.float64)

    @classmethod
    def from_vector(cls, v: np.ndarray) -> "Pose":
        v = np.asarray(v, dtype=np.float64)
        camera = np.array([[v[6], 0, v[7]], [0, v[6], v[8]], [0, 0, 1.0]])
        return cls(v[0:3].copy(), v[3:6].copy(), camera, float(v[9]))


POSE_FIELDS = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "cx", "cy", "rms")


@dataclass(frozen=True)
class Frontal:
    """A face warped into the canonical frontal frame.

    rgb : ndarray, shape (H, W, 3), uint8
    mask : ndarray, shape (H, W), bool — canonical pixels seen in the photo (not self-occluded)
    landmarks : ndarray, shape (68, 2), float64 — the photo's landmarks in the canonical frame
    """

    rgb: np.ndarray
    mask: np.ndarray
    landmarks: np.ndarray


class LandmarkBackend(Backend):
    """Kind ``landmarks``: find the subject's face and its 68 landmarks."""

    kind = "landmarks"

    def detect(self, image: np.ndarray, hint: np.ndarray | None = None) -> Landmarks:
        """image: (h, w, 3) uint8 RGB; hint: (68, 2) landmarks from a sidecar file, or None."""
        raise NotImplementedError


class PoseBackend(Backend):
    """Kind ``pose``: head pose from the 68 landmarks."""

    kind = "pose"

    def estimate(self, landmarks: np.ndarray, image_size: tuple[int, int]) -> Pose:
        """landmarks: (68, 2); image_size: (height, width) of the photo."""
        raise NotImplementedError


class FrontalizeBackend(Backend):
    """Kind ``frontalize``: warp a posed face into the canonical frontal frame."""

    kind = "frontalize"

    def frontalize(self, image: np.ndarray, landmarks: np.ndarray, pose: Pose) -> Frontal:
        raise NotImplementedError


@dataclass(frozen=True)
class Puppet:
    """What a renderer knows of the puppet (actor B), in the canonical frame.

    appearance : ndarray, shape (H, W, 3), float32 — B's face (e.g. the average), 0-255
    coverage : ndarray, shape (H, W), float32 — fraction of photos that saw each pixel
    fiducials : ndarray, shape (49, 2) — B's neutral (mean) fiducials
    """

    appearance: np.ndarray
    coverage: np.ndarray
    fiducials: np.ndarray


@dataclass(frozen=True)
class Rendered:
    """One output frame: rgb (h, w, 3) uint8, and mask (h, w) float32 in [0, 1] where the face is."""

    rgb: np.ndarray
    mask: np.ndarray


class RenderBackend(Backend):
    """Kind ``render``: the puppet performing one driver frame."""

    kind = "render"

    def render(self, puppet: Puppet, target: np.ndarray, pose: Pose, frame: np.ndarray) -> Rendered:
        """target: (49, 2) canonical fiducials to show; pose: the driver's head pose in this
        frame; frame: the driver's frame (h, w, 3) uint8 (its size, and a background)."""
        raise NotImplementedError
