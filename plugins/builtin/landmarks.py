"""Landmark backends: dlib's HOG detector + 68-point predictor, and sidecar files."""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from ..base import Params, Rejected
from ..hookspecs import hookimpl
from ..kinds import LandmarkBackend, Landmarks


@lru_cache(maxsize=1)
def dlib_models():
    """dlib's frontal face detector and the 68-point iBUG shape predictor.

    The predictor ships inside the ``face_recognition_models`` package: nothing is
    downloaded. Loaded once per process (about a second).
    """
    import dlib
    import face_recognition_models

    return (
        dlib.get_frontal_face_detector(),
        dlib.shape_predictor(face_recognition_models.pose_predictor_model_location()),
    )


#: dlib's frontal detector scans a pyramid of the image, each level 5/6 the size of the one before, and
#: its boxes are this many pixels square on the level that found them (its 80 px window less padding)
_LEVEL_BOX = 73
#: a face known to be ``face_height`` px tall is searched for from the level where faces of this share of
#: that height are found: finer levels, which hold most of the pixels, only find smaller faces
_SMALLEST_SHARE = 0.5


def pyramid_search(detector, image: np.ndarray, threshold: float, face_height: float | None):
    """dlib's detections (rectangles) in ``image`` at upsample 0, as ``detector.run`` finds them. With
    ``face_height``, the levels of dlib's pyramid that only find faces under :data:`_SMALLEST_SHARE` of
    it are skipped: the search starts on dlib's own downsampled image (the same pixels as those levels of a
    whole search), and each box is mapped back from the level that found it, so the boxes are a whole
    search's to the pixel. Faces smaller than that are not found; none found: a whole search."""
    import dlib

    skip = skipped_levels(face_height)
    if skip:
        pyramid, small = dlib.pyramid_down(6), image
        for _ in range(skip):
            small = pyramid(small)
        boxes = [_box_up(pyramid, r, skip) for r in detector.run(small, 0, threshold)[0]]
        if boxes and all(b is not None for b in boxes):
            return boxes
    return detector.run(image, 0, threshold)[0]


def skipped_levels(face_height: float | None) -> int:
    """How many of dlib's finest pyramid levels a search for a face ``face_height`` px tall skips: those
    whose boxes are under :data:`_SMALLEST_SHARE` of it (a level's boxes are 6/5 of the next finer one's)."""
    if not face_height:
        return 0
    return max(0, int(np.floor(np.log(_SMALLEST_SHARE * face_height / _LEVEL_BOX) / np.log(6 / 5))))


def _box_up(pyramid, rect, levels: int):
    """``rect``, a box dlib found in an image ``levels`` pyramid levels down, in the whole image's
    pixels as a whole search gives it: found again on the level it came from (a :data:`_LEVEL_BOX`
    square whose corners map up to ``rect``), then mapped up from there. None when no level fits."""
    import dlib

    found = dlib.drectangle(rect.left(), rect.top(), rect.right(), rect.bottom())
    for level in range(64):
        down = pyramid.rect_down(found, level)
        if down.width() < _LEVEL_BOX - 2:
            return None
        if down.width() > _LEVEL_BOX + 2:
            continue
        for left in (int(np.floor(down.left())), int(np.floor(down.left())) + 1):
            for top in (int(np.floor(down.top())), int(np.floor(down.top())) + 1):
                square = dlib.rectangle(left, top, left + _LEVEL_BOX - 1, top + _LEVEL_BOX - 1)
                if pyramid.rect_up(square, level) == rect:
                    return pyramid.rect_up(square, level + levels)
    return None


def choose_subject(boxes: np.ndarray, image_size: tuple[int, int], select: str) -> int:
    """Index of the subject among face boxes (n, 4) = (left, top, right, bottom).

    ``center``: the face nearest the image centre (the LFW convention);
    ``largest``: the largest face.
    """
    if select == "largest":
        return int(np.argmax((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])))
    h, w = image_size
    centres = (boxes[:, :2] + boxes[:, 2:]) / 2
    return int(np.argmin(np.hypot(centres[:, 0] - (w - 1) / 2, centres[:, 1] - (h - 1) / 2)))


class DlibLandmarks(LandmarkBackend):
    name = "dlib"
    description = "dlib HOG face detector + 68-point iBUG shape predictor (face_recognition_models)"
    default = True

    class Params(Params):
        select: Literal["center", "largest"] = Field(
            "center", description="which face is the subject when there are several: "
            "nearest the image centre (LFW convention) or the largest")
        upsample: int = Field(0, ge=0, le=3, description="dlib detector upsampling passes (x2 "
                              "each) of the first attempt; 0 finds faces from ~80 px, in a quarter of the time")
        retry_upsample: int | None = Field(1, ge=0, le=3, description="when the first attempt finds "
                                           "no face, retry with this many upsampling passes (none: no retry)")
        threshold: float = Field(0.0, ge=-2, le=2, description="dlib detector score threshold "
                                 "(adjust_threshold); lower finds more faces")
        small_side: int = Field(
            200, ge=0, description="images whose shorter side (px) is below this are padded and "
            "upsampled once before detection (tight crops such as 112x112, whose faces touch the border)")
        pad: float = Field(0.25, ge=0, le=1, description="padding per side of padded images, as a "
                           "fraction of the longer side")
        padded_threshold: float = Field(
            -0.4, ge=-2, le=2, description="detector threshold on padded images: a tight crop "
            "holds a face, so a weaker detection is accepted (raises the Glint360K rate 90%->95%)")
        retry_padded: bool = Field(True, description="when no face is found in a large image, "
                                   "retry padded")
        detect_side: int | None = Field(
            800, ge=64, description="images whose longer side (px) is above this are searched for faces "
            "first at this size (dlib's detector takes time in proportion to the pixels: 158 ms on a "
            "1600x900 frame, 39 at half its size), and at full size only when none is found there; the 68 "
            "points are always fitted at full size. Faces of HD clips are large; none: always full size")

    def attempts(self, image_size) -> list[tuple[float, bool, int, float]]:
        """(scale, padded, upsample, threshold) of each detection attempt, cheapest first."""
        p = self.params
        padded = (1.0, True, max(1, p.upsample), p.padded_threshold)
        if min(image_size) < p.small_side:
            return [padded]
        out = [(1.0, False, p.upsample, p.threshold)]
        if p.detect_side is not None and max(image_size) > p.detect_side:
            out.insert(0, (p.detect_side / max(image_size), False, p.upsample, p.threshold))
        if p.retry_upsample is not None and p.retry_upsample != p.upsample:
            out.append((1.0, False, p.retry_upsample, p.threshold))
        return out + ([padded] if p.retry_padded else [])

    def detect(self, image, hint=None, face_height: float | None = None):
        """The subject's landmarks. ``face_height``: how tall the face is in ``image`` (px) when the caller
        knows (the evaluation, which drew it): the search skips the detector's finest levels
        (:func:`pyramid_search`), with the same result."""
        import dlib

        detector, predictor = dlib_models()
        for scale, padded, upsample, threshold in self.attempts(image.shape[:2]):
            pad = int(round(self.params.pad * max(image.shape[:2]))) if padded else 0
            work = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REPLICATE) if pad else image
            work = np.ascontiguousarray(work)
            small = work if scale == 1 else cv2.resize(work, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            if upsample == 0:
                rects = pyramid_search(detector, small, threshold, face_height and face_height * scale)
            else:
                rects = detector.run(small, upsample, threshold)[0]
            if len(rects):
                break
        else:
            raise Rejected("no face found (dlib HOG detector)")
        boxes = np.array([[r.left(), r.top(), r.right(), r.bottom()] for r in rects], float) / scale - pad
        i = choose_subject(boxes, image.shape[:2], self.params.select)
        shape = predictor(work, dlib.rectangle(*(int(round(v)) for v in boxes[i] + pad)))  # at full size
        points = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64) - pad
        return Landmarks(points=points, box=boxes[i], n_faces=len(rects))


class SidecarLandmarks(LandmarkBackend):
    name = "sidecar"
    description = "landmarks read from a sidecar file beside each photo (iBUG .pts; synthetic ground truth)"

    class Params(Params):
        pass

    def detect(self, image, hint=None):
        if hint is None or not np.all(np.isfinite(hint)):
            raise Rejected("no landmark sidecar (.pts) beside this photo")
        points = np.asarray(hint, dtype=np.float64)
        box = np.r_[points.min(axis=0), points.max(axis=0)]
        return Landmarks(points=points, box=box, n_faces=1)


@hookimpl
def persona_register_backends(register):
    register(DlibLandmarks)
    register(SidecarLandmarks)
