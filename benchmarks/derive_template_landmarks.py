"""Derive the 2D layout of the generic template's 68 landmarks from real photos.

Runs dlib's HOG detector and 68-point iBUG predictor over LFW photo collections, keeps
the near-frontal faces, aligns all shapes by generalised Procrustes (translation,
rotation, uniform scale), symmetrises the mean left/right and prints it in the
template's normalised coordinates ``X = (x - 97)/80, Y = (y - 112)/80``:

* the eye centres (mean of points 36-41 and 42-47) lie at ``X = -/+ EYE_X``, ``Y = EYE_Y``
  (the analytic face's eye sockets, ALGORITHMS §3.2);
* the image left/right mirror pairs of the iBUG scheme are averaged (x negated).

The printed table is pasted into ``plugins/face/template.py`` (``_LM68``). Usage::

    .venv/bin/python benchmarks/derive_template_landmarks.py [collection_dir ...]

Default collections: george_w_bush and colin_powell under /work/shared/data/collections.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import dlib
import face_recognition_models
import numpy as np

DATA = Path("/work/shared/data/collections")
DEFAULT_COLLECTIONS = ("george_w_bush", "colin_powell")

EYE_X = 0.41  # half inter-ocular distance of the template, normalised units
EYE_Y = -0.22
MAX_YAW_ASYM = 0.06  # |nose tip x - eye midpoint x| / inter-ocular distance
MAX_JAW_ASYM = 0.10  # relative difference of the nose-to-jaw-side distances
MAX_ROLL_DEG = 10.0

MIRROR = np.array(
    list(range(16, -1, -1))                  # jaw 0..16
    + list(range(26, 16, -1))                # brows 17..26
    + [27, 28, 29, 30]                       # nose bridge
    + [35, 34, 33, 32, 31]                   # lower nose
    + [45, 44, 43, 42, 47, 46]               # right eye 36..41 <-> left eye 42..47
    + [39, 38, 37, 36, 41, 40]
    + [54, 53, 52, 51, 50, 49, 48]           # outer lips 48..54
    + [59, 58, 57, 56, 55]                   # outer lips 55..59
    + [64, 63, 62, 61, 60]                   # inner lips 60..64
    + [67, 66, 65]                           # inner lips 65..67
)
assert sorted(MIRROR.tolist()) == list(range(68))
assert np.all(MIRROR[MIRROR] == np.arange(68))


def eye_centres(shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return shape[36:42].mean(axis=0), shape[42:48].mean(axis=0)


def detect_shapes(paths: list[Path]) -> tuple[list[np.ndarray], int]:
    detector = dlib.get_frontal_face_detector()
    predictor = dlib.shape_predictor(face_recognition_models.pose_predictor_model_location())
    shapes = []
    n_detected = 0
    for path in paths:
        bgr = cv2.imread(str(path))
        if bgr is None:
            continue
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        rects = detector(rgb, 1)
        if len(rects) == 0:
            continue
        n_detected += 1
        h, w = rgb.shape[:2]
        # LFW centres the named person: keep the detection closest to the image centre.
        rect = min(
            rects,
            key=lambda r: ((r.left() + r.right()) / 2 - w / 2) ** 2 + ((r.top() + r.bottom()) / 2 - h / 2) ** 2,
        )
        det = predictor(rgb, rect)
        shapes.append(np.array([[p.x, p.y] for p in det.parts()], dtype=np.float64))
    return shapes, n_detected


def is_frontal(shape: np.ndarray) -> bool:
    er, el = eye_centres(shape)
    iod = np.linalg.norm(el - er)
    d = el - er
    roll = np.degrees(np.arctan2(d[1], d[0]))
    # Express in the eye frame so roll does not masquerade as yaw.
    c, s = d / iod
    rot = np.array([[c, s], [-s, c]])
    p = (shape - (er + el) / 2) @ rot.T
    yaw_asym = abs(p[30, 0]) / iod
    dl = np.linalg.norm(p[30] - p[0])
    dr = np.linalg.norm(p[30] - p[16])
    jaw_asym = abs(dl - dr) / (dl + dr)
    return abs(roll) < MAX_ROLL_DEG and yaw_asym < MAX_YAW_ASYM and jaw_asym < MAX_JAW_ASYM


def similarity_align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Umeyama/Procrustes: the similarity transform of src that best fits dst (no reflection)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    u, sig, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    corr = np.diag([1.0, d])
    rot = u @ corr @ vt
    scale = (sig * np.diag(corr)).sum() / (a**2).sum()
    return scale * a @ rot.T + md


def generalised_procrustes(shapes: np.ndarray, iterations: int = 20) -> np.ndarray:
    mean = shapes[0].copy()
    for _ in range(iterations):
        aligned = np.stack([similarity_align(s, mean) for s in shapes])
        new_mean = aligned.mean(axis=0)
        new_mean = similarity_align(new_mean, shapes[0])  # fix the gauge (scale/rotation of the first shape)
        if np.abs(new_mean - mean).max() < 1e-9:
            break
        mean = new_mean
    return mean, aligned


def normalise(mean: np.ndarray) -> np.ndarray:
    er, el = eye_centres(mean)
    d = el - er
    iod = np.linalg.norm(d)
    c, s = d / iod
    rot = np.array([[c, s], [-s, c]])
    p = (mean - (er + el) / 2) @ rot.T * (2 * EYE_X / iod)
    p[:, 1] += EYE_Y
    sym = p[MIRROR] * np.array([-1.0, 1.0])
    return (p + sym) / 2


def main(argv: list[str]) -> None:
    dirs = [Path(a) for a in argv] or [DATA / c for c in DEFAULT_COLLECTIONS]
    paths = sorted(p for d in dirs for p in d.glob("*.jpg"))
    shapes, n_detected = detect_shapes(paths)
    frontal = [s for s in shapes if is_frontal(s)]
    mean, aligned = generalised_procrustes(np.stack(frontal))
    out = normalise(mean)
    # spread of the aligned shapes around the mean, in inter-ocular units (how well-defined the mean is)
    er, el = eye_centres(mean)
    iod = np.linalg.norm(el - er)
    spread = np.sqrt(((aligned - mean) ** 2).sum(axis=2).mean(axis=0)) / iod
    print(f"# photos: {len(paths)}, detected: {n_detected}, near-frontal used: {len(frontal)}")
    print(f"# per-point RMS spread / IOD: mean {spread.mean():.3f}, max {spread.max():.3f}")
    print("_LM68 = np.array([")
    for i, (x, y) in enumerate(out):
        print(f"    [{x:+.4f}, {y:+.4f}],  # {i}")
    print("])")


if __name__ == "__main__":
    main(sys.argv[1:])
