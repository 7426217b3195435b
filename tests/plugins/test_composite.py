"""The multi-band composite of B's render into A's frame, and the seam measure
(persona.plugins.face.composite), on synthetic images with known answers."""

from __future__ import annotations

import cv2
import numpy as np

from persona.plugins.face import composite


def scene(size=200, radius=60):
    """A dark frame with its own fine texture, a light face with a checker pattern, and a disk mask
    feathered over 3 px (as the renderer's)."""
    rng = np.random.default_rng(0)
    frame = np.clip(60 + rng.normal(0, 4, (size, size, 3)), 0, 255).astype(np.uint8)
    ys, xs = np.mgrid[0:size, 0:size]
    checker = ((ys // 2 + xs // 2) % 2) * 30 - 15
    face = np.clip(200 + checker[..., None] + np.zeros(3), 0, 255).astype(np.uint8)
    disk = ((ys - size / 2) ** 2 + (xs - size / 2) ** 2 <= radius ** 2).astype(np.float32)
    alpha = cv2.GaussianBlur(disk, (0, 0), 3.0) * disk
    return face, frame, alpha, disk.astype(bool)


def test_multiband_spreads_the_colour_step_and_keeps_the_detail():
    face, frame, alpha, disk = scene()
    a = alpha[..., None]
    paste = np.round(face * a + frame * (1 - a)).astype(np.uint8)
    blended = composite.multiband(face, frame, alpha)
    before, after = composite.seam(paste, frame, alpha), composite.seam(blended, frame, alpha)
    print(f"\npaste {before}, multiband {after}")
    assert after["colour_step"] < 0.7 * before["colour_step"]
    assert after["gradient_ratio"] < 0.7 * before["gradient_ratio"]
    centre = blended[80:120, 80:120].astype(float)
    assert abs(centre.mean() - 200) < 25  # B's tone in the middle of the face
    assert abs(centre.std() - face[80:120, 80:120].astype(float).std()) < 3  # and B's fine detail
    # no halo of B's tone in A's frame just outside the face (8.4 grey levels measured on a 2-8 px
    # ring; 15.8 when every level's weights came from the mask itself)
    d = disk.astype(np.uint8)
    ring = (cv2.dilate(d, np.ones((17, 17), np.uint8)) > 0) & ~(cv2.dilate(d, np.ones((5, 5), np.uint8)) > 0)
    assert np.abs(blended[ring].astype(float) - frame[ring]).mean() < 11
    far = ~cv2.dilate(disk.astype(np.uint8), np.ones((41, 41), np.uint8)).astype(bool)
    assert np.abs(blended[far].astype(int) - frame[far].astype(int)).max() <= 2  # A's frame away from it


def test_seam_of_the_frame_itself_and_edge_cases():
    face, frame, alpha, _ = scene()
    same = composite.seam(frame, frame, alpha)
    assert abs(same["colour_step"]) < 1e-9 and abs(same["gradient_ratio"] - 1) < 1e-9
    assert composite.seam(frame, frame, np.zeros_like(alpha)) is None
    assert np.array_equal(composite.multiband(face, frame, np.zeros_like(alpha)), frame)
    assert composite.levels_for(alpha) == 4  # a 120-px face: down to about 30 px
