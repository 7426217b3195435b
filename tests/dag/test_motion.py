"""The driver <-> puppet correspondence φ (ALGORITHMS §7.3) against a known warp.

The puppet's "average" is the driver's face image warped by a known smooth displacement, so the
true φ (puppet px -> driver px) is known; the driver's basis is that face's Lambertian basis."""

import cv2
import numpy as np
from persona.plugins.face.transfer import correspondence
from persona.plugins.builtin.flow import VariationalRefinementFlow
from persona.plugins.face.synthetic import make_face
from persona.plugins.face.template import FaceIdentity


def scene():
    face = make_face(FaceIdentity.random(np.random.default_rng(4)))
    light = np.array([0.5, 0.3, -0.2, -0.7])
    rows = np.stack([face.albedo] + [face.albedo * face.normals[..., k:k + 1] for k in range(3)])  # (4, H, W, 3)
    image = np.clip(np.tensordot(light, rows, 1), 0, 1) * face.mask[..., None]
    h, w = face.mask.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = np.stack([xs + 3 * np.sin(ys / 30), ys + 2 * np.cos(xs / 25)], axis=-1).astype(np.float32)
    average = cv2.remap(image.astype(np.float32), truth[..., 0], truth[..., 1], cv2.INTER_LINEAR) * 255
    mask = cv2.erode(face.mask.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=8).astype(bool)
    return average, mask, rows.astype(np.float32), truth


def error(phi, truth, mask):
    return float(np.median(np.linalg.norm(phi[mask] - truth[mask], axis=-1)))


def test_flow_finds_the_known_warp_and_a_guide_is_only_corrected():
    average, mask, basis, truth = scene()
    flow = VariationalRefinementFlow()
    h, w = mask.shape
    identity = np.stack(np.mgrid[0:h, 0:w][::-1], axis=-1).astype(np.float32)
    plain = correspondence(average, mask, basis, flow)
    exact = correspondence(average, mask, basis, flow, guide=truth)
    halfway = correspondence(average, mask, basis, flow, guide=(identity + truth) / 2)
    print(f"\nmedian |φ - truth| px: identity {error(identity, truth, mask):.2f}, flow {error(plain, truth, mask):.2f}, "
          f"exact guide {error(exact, truth, mask):.2f}, halfway guide {error(halfway, truth, mask):.2f}")
    assert error(plain, truth, mask) < 0.3 * error(identity, truth, mask)
    assert error(exact, truth, mask) < 0.2
    assert error(halfway, truth, mask) < 0.3 * error((identity + truth) / 2, truth, mask)
