"""Head pose by PnP of the detected landmarks against the generic 3D template."""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from ..base import Params, Rejected
from ..face.template import IDX49, generic_template
from ..hookspecs import hookimpl
from ..kinds import Pose, PoseBackend


def default_camera(image_size: tuple[int, int], focal_factor: float) -> np.ndarray:
    """Intrinsics for a photo of unknown camera: f = c * max(h, w), principal point at the centre."""
    h, w = image_size
    f = focal_factor * max(h, w)
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


#: the landmarks (iBUG 68 indices) each choice of ``points`` poses a face from. The paper's 49 fiducials
#: hold the mouth, the lids and the brows, which the expression moves: on a video of a woman opening her
#: mouth, PnP on them pitches her head back by 51° per inter-ocular distance of opening. "rigid" is
#: the nose and the eyes' corners (docs/expression.md, "The head's pose from the nose and the eyes' corners:
#: tried, a switch"); "weighted" is the 49 with those rigid points listed three times, which a least-squares
#: fit weighs three times
RIGID = [36, 39, 42, 45, *range(27, 36)]
POINTS = {"fiducials49": list(IDX49), "all68": list(range(68)), "rigid": RIGID, "weighted": list(IDX49) + 2 * RIGID}


def solve_pose(points3d: np.ndarray, points2d: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """rvec, tvec mapping points3d (n, 3) onto points2d (n, 2): EPnP, then Levenberg-Marquardt."""
    obj = np.ascontiguousarray(points3d, dtype=np.float64)
    img = np.ascontiguousarray(points2d, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera, None, flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        raise Rejected("pose: PnP failed")
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera, None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise Rejected("pose: PnP refinement failed")
    return rvec.ravel(), tvec.ravel()


class PnPPose(PoseBackend):
    name = "pnp"
    description = "PnP (EPnP + iterative) of the landmarks against the generic analytic 3D face"
    default = True

    class Params(Params):
        focal_factor: float = Field(1.2, gt=0.2, le=10, description="focal length as a multiple "
                                    "of the photo's longer side (unknown Internet cameras); 0.7 is a phone's or a "
                                    "webcam's, filming close (docs/expression.md, 'The camera')")
        points: Literal["fiducials49", "rigid", "weighted", "all68"] = Field(
            "fiducials49", description="landmarks the pose is solved from: the paper's 49 fiducials (no jaw "
            "contour, which slides with the view), whose mouth and brows tilt the head as they move; 'rigid', the "
            "nose and the eyes' corners, which the expression moves least (not in the paper; steadier drives by a "
            "woman's open mouth, but worse from tight 112-px crops: docs/expression.md); 'weighted', the 49 with "
            "the rigid ones counted three times (not in the paper; better self-reenactments of HD clips, but a "
            "mouth that opens less when another person drives: docs/expression.md); or all 68 (POINTS)")
        max_rms: float = Field(0.2, gt=0, description="reject poses whose landmark reprojection "
                               "RMS exceeds this fraction of the inter-ocular distance")

    def estimate(self, landmarks, image_size):
        template = generic_template()
        fitted = POINTS[self.params.points]
        idx = sorted(set(fitted))  # each point once: what the checks below judge
        camera = default_camera(image_size, self.params.focal_factor)
        rvec, tvec = solve_pose(template.landmarks3d[fitted], landmarks[fitted], camera)
        rotation = cv2.Rodrigues(rvec)[0]
        depth = template.landmarks3d[idx] @ rotation.T + tvec
        if np.any(depth[:, 2] <= 0):
            raise Rejected("pose: PnP put the face behind the camera")
        if rotation[2, 2] <= 0.05:  # the template's forward axis (0, 0, 1) must still face away
            raise Rejected("pose: face turned away from the camera (|yaw| or |pitch| near 90°)")
        projected = cv2.projectPoints(template.landmarks3d[idx], rvec, tvec, camera, None)[0][:, 0]
        rms = float(np.sqrt(np.mean(np.sum((projected - landmarks[idx]) ** 2, axis=1))))
        eyes = np.linalg.norm(landmarks[36:42].mean(0) - landmarks[42:48].mean(0))
        if rms > self.params.max_rms * eyes:
            raise Rejected(f"pose: landmarks do not fit a face (reprojection RMS {rms:.1f} px "
                           f"> {self.params.max_rms:g} x inter-ocular {eyes:.1f} px)")
        return Pose(rvec=rvec, tvec=tvec, camera=camera, rms=rms)


@hookimpl
def persona_register_backends(register):
    register(PnPPose)
