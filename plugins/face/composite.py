"""B's rendered face in A's frame: a multi-band composite, and a measure of its seam.

Pasting the render through its soft mask (``face α + frame (1 - α)``) leaves a visible edge
wherever B's skin tone or lighting differs from A's around it: the step is as sharp as the mask's
few-pixel feather. Multi-band blending (Burt & Adelson 1983) blends each band of a Laplacian
pyramid through the mask's Gaussian pyramid at the same level: fine detail switches from A to B
over a pixel or two, while the low frequencies (skin tone, lighting) cross over a width that
grows with the band, so the colour step is spread over a good part of the face instead of the
feather. Each level's weights come from the mask eroded by half that level's pixel, so the
coarse transitions lie inside B's face: without that, B's tone spilled as a light halo into A's
hair. Inside the face B's own detail and, away from the edge, B's own tone remain.

The seam is measured on a ring along the mask's edge (``seam``): the colour step across it (the
mean colour a few pixels inside minus that a few pixels outside, against the same step in A's own
frame) and the gradient energy on it over that of A's frame there (1 = as smooth as the frame).
"""

from __future__ import annotations

import cv2
import numpy as np


def levels_for(mask: np.ndarray) -> int:
    """Pyramid levels for a face mask: until the coarsest level's pixel is about a quarter of the
    face's smaller side (at least 1)."""
    ys, xs = np.nonzero(mask > 0.5)
    if len(ys) == 0:
        return 1
    side = min(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1)
    return int(max(1, np.floor(np.log2(max(side, 1) / 4))))


def _level_weights(alpha: np.ndarray, levels: int) -> list[np.ndarray]:
    """The blending weight of each pyramid level 0..levels: the mask eroded by half the level's
    pixel (2^k / 2 px), then reduced to the level's size. The coarse levels' transitions lie inside
    B's face, so B's tone does not spill as a halo into A's hair and background."""
    weights = []
    for k in range(levels + 1):
        r = 2 ** k // 2
        w = cv2.erode(alpha, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) if r else alpha
        for _ in range(k):
            w = cv2.pyrDown(w)
        weights.append(w)
    return weights


def multiband(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, levels: int | None = None) -> np.ndarray:
    """The composite (h, w, 3) uint8 of ``face`` over ``frame`` (both (h, w, 3) uint8) with the soft
    mask ``alpha`` (h, w) in [0, 1]. Outside the mask the face image is replaced by the frame (the
    render's background must not bleed into the low bands). ``levels``: by default
    :func:`levels_for`."""
    alpha = np.clip(np.asarray(alpha, np.float32), 0, 1)
    if levels is None:
        levels = levels_for(alpha)
    a = alpha[..., None]
    top = np.asarray(face, np.float32) * a + np.asarray(frame, np.float32) * (1 - a)
    bottom = np.asarray(frame, np.float32)
    bands_top, bands_bottom = [], []
    for _ in range(levels):
        small_top, small_bottom = cv2.pyrDown(top), cv2.pyrDown(bottom)
        size = (top.shape[1], top.shape[0])
        bands_top.append(top - cv2.pyrUp(small_top, dstsize=size))
        bands_bottom.append(bottom - cv2.pyrUp(small_bottom, dstsize=size))
        top, bottom = small_top, small_bottom
    weights = _level_weights(alpha, levels)
    w = weights[levels][..., None]
    out = top * w + bottom * (1 - w)
    for k in reversed(range(levels)):
        out = cv2.pyrUp(out, dstsize=(bands_top[k].shape[1], bands_top[k].shape[0]))
        w = weights[k][..., None]
        out = out + bands_top[k] * w + bands_bottom[k] * (1 - w)
    return np.clip(out, 0, 255).round().astype(np.uint8)


def seam(image: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, reach: int = 4) -> dict | None:
    """The seam of a composite ``image`` over ``frame`` along the edge of the mask ``alpha`` (all
    (h, w[, 3])): ``colour_step`` — |mean colour on a ring ``reach`` px inside the edge minus that
    ``reach`` px outside|, in grey levels (Euclidean over RGB), minus the same in ``frame``;
    ``gradient_ratio`` — the mean squared gradient on the edge's ring (±``reach`` px) in the image
    over the frame's there. None when the mask has no edge."""
    face = (np.asarray(alpha) > 0.5).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    grown, shrunk = cv2.dilate(face, kernel), cv2.erode(face, kernel)
    inner = (shrunk > 0) & (cv2.erode(face, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * reach + 1,) * 2)) == 0)
    outer = (grown == 0) & (cv2.dilate(face, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * reach + 1,) * 2)) > 0)
    ring = (grown > 0) & (shrunk == 0)
    if not (inner.any() and outer.any() and ring.any()):
        return None

    def step(img):
        img = np.asarray(img, np.float64)
        return float(np.linalg.norm(img[inner].mean(axis=0) - img[outer].mean(axis=0)))

    def energy(img):
        grey = cv2.cvtColor(np.asarray(img, np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float64)
        gx, gy = cv2.Sobel(grey, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_64F, 0, 1, ksize=3)
        return float(np.mean((gx ** 2 + gy ** 2)[ring]))

    return {"colour_step": step(image) - step(frame), "gradient_ratio": energy(image) / max(energy(frame), 1e-9)}


def paste(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The plain composite through the soft mask, ``face α + frame (1 - α)``, uint8 (for comparison)."""
    a = np.clip(np.asarray(alpha, np.float32), 0, 1)[..., None]
    return np.round(np.asarray(face, np.float32) * a + np.asarray(frame, np.float32) * (1 - a)).astype(np.uint8)


def seams(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray,
          blended: np.ndarray | None = None) -> dict[str, dict | None]:
    """:func:`seam` of the :func:`multiband` composite (``blended``, when made already) and of the
    :func:`paste`, keyed by those names."""
    blended = multiband(face, frame, alpha) if blended is None else blended
    return {"multiband": seam(blended, frame, alpha),
            "paste": seam(paste(face, frame, alpha), frame, alpha)}
