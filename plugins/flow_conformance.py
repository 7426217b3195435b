"""Conformance tests that any ``flow`` backend (built-in or third-party) can run.

Subclass :class:`FlowBackendTests` in a test module (its name starts with ``Test`` there)::

    from persona.plugins.flow_conformance import FlowBackendTests

    class TestMyFlow(FlowBackendTests):
        backend = MyFlow()          # an instance
        epe_tolerance = 0.2         # px; class attributes a subclass may tighten or relax
        identity_tolerance = 0.02   # px
        handles_brightness = True   # False for backends without gradient constancy

The pairs are seeded textured images (multi-scale filtered noise on a skin colour, like the
synthetic albedo of ALGORITHMS §3.2) and known smooth warps (affine + sinusoid, |w| <= 3 px),
at the paper's face size 194 x 244 (W x H). The convention checked is ALGORITHMS §0:
``w = flow(I0, I1)`` lives on I0's grid and ``I0(x) ≈ I1(x + w(x))``.

This module needs pytest and numpy/OpenCV only; its class name does not start with "Test",
so pytest does not collect it by itself.
"""

from __future__ import annotations

from typing import ClassVar

import cv2
import numpy as np
import pytest

#: canonical face size (H, W) of the paper, ALGORITHMS §0
FACE_SHAPE = (244, 194)
SKIN = np.array([0.78, 0.58, 0.47])


def textured_image(shape: tuple[int, int], seed: int, pad: int = 0, amplitude: float = 0.035,
                   colour: bool = True) -> np.ndarray:
    """A float64 image in [0, 1], (H + 2 pad, W + 2 pad[, 3]): skin colour times
    (1 + noise filtered at sigma 1, 3 and 8 px, each with std ``amplitude``), plus a weaker
    per-channel noise so that the colour channels carry texture too."""
    h, w = shape[0] + 2 * pad, shape[1] + 2 * pad
    rng = np.random.default_rng(seed)

    def noise(sigma):
        n = cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return n / n.std()

    lum = sum(amplitude * noise(s) for s in (1.0, 3.0, 8.0))
    img = SKIN * (1 + lum)[:, :, None]
    img = img + np.stack([0.3 * amplitude * noise(2.0) for _ in range(3)], axis=-1) * SKIN
    img = np.clip(img, 0, 1)
    if not colour:
        img = img @ np.array([0.299, 0.587, 0.114])
    return img


def smooth_warp(shape: tuple[int, int], seed: int, max_norm: float = 3.0) -> np.ndarray:
    """A smooth flow (H, W, 2) float64: random affine plus a sinusoid, scaled so max |w| = max_norm."""
    h, w = shape
    rng = np.random.default_rng(seed + 1000)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    xn, yn = (x - w / 2) / (w / 2), (y - h / 2) / (h / 2)
    flow = np.empty((h, w, 2))
    for c in range(2):
        t, a, b = rng.uniform(-1, 1, 3)
        amp, kx, ky, ph = rng.uniform(0.5, 1.0), rng.uniform(1, 2.5), rng.uniform(1, 2.5), rng.uniform(0, 2 * np.pi)
        flow[:, :, c] = t + a * xn + b * yn + amp * np.sin(np.pi * (kx * xn + ky * yn) + ph)
    return flow * (max_norm / np.linalg.norm(flow, axis=-1).max())


def warped_pair(shape: tuple[int, int] = FACE_SHAPE, seed: int = 0, colour: bool = True,
                max_norm: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image0, image1, w) with image0(x) = image1(x + w(x)) exactly up to interpolation:
    image1 is a crop of a larger texture and image0 samples that texture at x + w(x)."""
    pad = 12
    texture = textured_image(shape, seed, pad=pad, colour=colour).astype(np.float32)
    w = smooth_warp(shape, seed, max_norm)
    h, wd = shape
    y, x = np.mgrid[0:h, 0:wd].astype(np.float32)
    map_x = (x + pad + w[:, :, 0]).astype(np.float32)
    map_y = (y + pad + w[:, :, 1]).astype(np.float32)
    image0 = cv2.remap(texture, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    image1 = texture[pad:pad + h, pad:pad + wd]
    return (np.clip(image0, 0, 1).astype(np.float64), np.ascontiguousarray(image1, np.float64), w)


def remap(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """image sampled at x + flow(x) (the backward warp of ALGORITHMS §0)."""
    h, w = flow.shape[:2]
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return cv2.remap(np.asarray(image, np.float32), x + flow[:, :, 0].astype(np.float32),
                     y + flow[:, :, 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def interior(a: np.ndarray, border: int) -> np.ndarray:
    return a[border:a.shape[0] - border, border:a.shape[1] - border]


def end_point_error(flow: np.ndarray, truth: np.ndarray, border: int = 8) -> float:
    """Mean end-point error in px over the interior (a border of ``border`` px is ignored)."""
    return float(np.mean(np.linalg.norm(interior(flow - truth, border), axis=-1)))


# the known-warp cases: (seed, colour)
WARP_CASES = [(0, True), (1, False)]


class FlowBackendTests:
    """Mix-in of conformance tests for a :class:`persona.plugins.kinds.FlowBackend`."""

    backend: ClassVar = None
    #: mean end-point error (px) allowed on the known smooth warps, interior only
    epe_tolerance: ClassVar[float] = 0.2
    #: mean |w| (px) allowed on an identical pair
    identity_tolerance: ClassVar[float] = 0.02
    #: the backend claims gradient constancy: a +0.05 brightness offset leaves the flow ~0
    handles_brightness: ClassVar[bool] = True
    #: mean |w| (px) allowed under the brightness offset
    brightness_tolerance: ClassVar[float] = 0.1
    #: remapping image1 by the flow must cut the mean |I0 - I1| residual to this fraction
    remap_tolerance: ClassVar[float] = 0.25
    #: border (px) ignored by the error measures (the flow there may point outside image1)
    border: ClassVar[int] = 8

    # -- helpers --------------------------------------------------------------------------

    def flow(self, image0, image1, mask=None) -> np.ndarray:
        w = self.backend.flow(image0, image1, mask)
        self.check_contract(w, np.shape(image0)[:2])
        return w

    @staticmethod
    def check_contract(w, shape):
        assert isinstance(w, np.ndarray), f"flow() returned {type(w).__name__}, not an ndarray"
        assert w.shape == (*shape, 2), f"flow shape {w.shape}, expected {(*shape, 2)}"
        assert w.dtype == np.float32, f"flow dtype {w.dtype}, expected float32"
        assert np.all(np.isfinite(w)), "flow has NaN or infinite values"

    def known_case(self, seed: int, colour: bool):
        cache = type(self).__dict__.get("_known_cache")
        if cache is None:
            cache = {}
            type(self)._known_cache = cache
        key = (seed, colour)
        if key not in cache:
            i0, i1, truth = warped_pair(FACE_SHAPE, seed=seed, colour=colour)
            cache[key] = (i0, i1, truth, self.flow(i0, i1))
        return cache[key]

    # -- accuracy -------------------------------------------------------------------------

    @pytest.mark.parametrize("seed,colour", WARP_CASES, ids=["rgb", "grey"])
    def test_known_smooth_warp_epe(self, seed, colour):
        _, _, truth, w = self.known_case(seed, colour)
        epe = end_point_error(w, truth, self.border)
        assert epe < self.epe_tolerance, (
            f"{self.backend!r}: mean end-point error {epe:.3f} px >= {self.epe_tolerance} px")

    @pytest.mark.parametrize("seed,colour", WARP_CASES, ids=["rgb", "grey"])
    def test_known_smooth_warp_direction(self, seed, colour):
        """The flow points the way of the convention, not the opposite (a sign or swap bug)."""
        _, _, truth, w = self.known_case(seed, colour)
        epe = end_point_error(w, truth, self.border)
        assert epe < end_point_error(-w, truth, self.border)
        assert epe < end_point_error(w[:, :, ::-1], truth, self.border) or np.allclose(
            truth[:, :, 0], truth[:, :, 1])

    @pytest.mark.parametrize("seed,colour", WARP_CASES, ids=["rgb", "grey"])
    def test_remap_reproduces_image0(self, seed, colour):
        i0, i1, _, w = self.known_case(seed, colour)
        before = np.mean(np.abs(interior(i1 - i0, self.border)))
        after = np.mean(np.abs(interior(remap(i1, w) - i0, self.border)))
        assert after < self.remap_tolerance * before, (
            f"{self.backend!r}: remap(image1, w) leaves a residual {after:.4f}, "
            f"more than {self.remap_tolerance} x the unwarped residual {before:.4f}")

    def test_identity_pair(self):
        i0 = textured_image(FACE_SHAPE, seed=5)
        w = self.flow(i0, i0.copy())
        mean = float(np.mean(np.linalg.norm(w, axis=-1)))
        assert mean < self.identity_tolerance, (
            f"{self.backend!r}: identical images give mean |w| = {mean:.4f} px "
            f">= {self.identity_tolerance} px")

    def test_brightness_offset(self):
        if not self.handles_brightness:
            pytest.skip(f"{type(self.backend).__name__} does not claim gradient constancy")
        i0 = textured_image(FACE_SHAPE, seed=6)
        w = self.flow(i0, np.clip(i0 + 0.05, 0, 1))
        mean = float(np.mean(np.linalg.norm(interior(w, self.border), axis=-1)))
        assert mean < self.brightness_tolerance, (
            f"{self.backend!r}: a +0.05 brightness offset gives mean |w| = {mean:.3f} px "
            f">= {self.brightness_tolerance} px")

    # -- mask -----------------------------------------------------------------------------

    def test_mask(self):
        """image0 is black outside an elliptic face mask; with the mask the flow inside is right."""
        i0, i1, truth = warped_pair(FACE_SHAPE, seed=2)
        h, w = FACE_SHAPE
        y, x = np.mgrid[0:h, 0:w]
        mask = ((x - w / 2) / (0.42 * w)) ** 2 + ((y - h / 2) / (0.45 * h)) ** 2 <= 1
        i0 = np.where(mask[:, :, None], i0, 0.0)  # a hard background edge, as a masked face
        flow = self.flow(i0, i1, mask)
        inside = mask & (cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0)
        err = float(np.mean(np.linalg.norm((flow - truth)[inside], axis=-1)))
        assert err < self.epe_tolerance, (
            f"{self.backend!r}: image0 black outside a mask: with the mask passed, the mean "
            f"end-point error inside it is {err:.3f} px >= {self.epe_tolerance} px (the flow "
            "latches onto the mask edge?)")

    def test_empty_and_full_mask(self):
        i0, i1, _ = warped_pair(FACE_SHAPE, seed=3)
        for mask in (np.zeros(FACE_SHAPE, bool), np.ones(FACE_SHAPE, bool)):
            self.flow(i0, i1, mask)

    # -- dtype and shape contract ---------------------------------------------------------

    @pytest.mark.parametrize("kind", ["grey64", "grey32", "rgb32", "rgb_uint8", "grey_uint8"])
    def test_dtypes(self, kind):
        i0, i1, _ = warped_pair((122, 97), seed=4, colour=kind.startswith("rgb"), max_norm=1.5)
        if kind.endswith("32"):
            i0, i1 = i0.astype(np.float32), i1.astype(np.float32)
        elif kind.endswith("uint8"):
            i0, i1 = (np.rint(a * 255).astype(np.uint8) for a in (i0, i1))
        self.flow(i0, i1)

    @pytest.mark.parametrize("shape", [(122, 97), (97, 122), (33, 47)])
    def test_odd_sizes(self, shape):
        i0, i1, _ = warped_pair(shape, seed=7, max_norm=1.0)
        self.flow(i0, i1)

    def test_inputs_not_modified(self):
        i0, i1, _ = warped_pair((122, 97), seed=8)
        c0, c1 = i0.copy(), i1.copy()
        self.flow(i0, i1)
        assert np.array_equal(i0, c0) and np.array_equal(i1, c1)

    @pytest.mark.parametrize("case", ["size", "channels", "ndim", "mask"])
    def test_bad_input_raises(self, case):
        i0 = textured_image((40, 50), seed=9)
        if case == "size":
            args = (i0, i0[:-1])
        elif case == "channels":
            args = (i0, i0[:, :, 0])
        elif case == "ndim":
            args = (i0[None], i0[None])
        else:
            args = (i0, i0, np.ones((39, 50), bool))
        with pytest.raises(ValueError, match="shape"):
            self.backend.flow(*args)
