"""Conformance tests that any ``denoise`` backend (built-in or third-party) can run.

Subclass :class:`DenoiseBackendTests` in a test module (its name starts with ``Test`` there)::

    from persona.plugins.denoise_conformance import DenoiseBackendTests

    class TestMyDenoiser(DenoiseBackendTests):
        backend = MyDenoiser()      # an instance
        constant_tolerance = 1e-3   # class attributes a subclass may tighten or relax

What is checked is the contract of :meth:`persona.plugins.kinds.DenoiseBackend.denoise`, which the
deformation transfer relies on (ALGORITHMS §10-11): a (H, W) float64 result; the values off the mask
(and non-finite ones) carry no data, so they cannot change the result on the mask; the inputs are left
as they were; the same input gives the same output; a constant field stays that constant; a noisy step
ends no further from the clean step than it started (the identity passes: it moves nothing); and
malformed inputs raise ValueError (TypeError for a mask that is not boolean).

This module needs pytest and numpy only; its class name does not start with "Test", so pytest does not
collect it by itself.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest


def noisy_step(seed: int = 0, sigma: float = 0.5, shape: tuple[int, int] = (48, 48), step: float = 2.0):
    """A clean step (H, W) float64, 0 on the left half and ``step`` on the right, and it plus Gaussian
    noise of std ``sigma`` (seeded)."""
    clean = np.where(np.arange(shape[1]) >= shape[1] // 2, step, 0.0)[None, :].repeat(shape[0], 0)
    return clean, clean + np.random.default_rng(seed).normal(0.0, sigma, shape)


def with_a_hole(shape: tuple[int, int]) -> np.ndarray:
    """A mask (H, W) bool: everything but a rectangle in the middle."""
    mask = np.ones(shape, bool)
    h, w = shape
    mask[h // 3:h // 2, w // 5:(4 * w) // 5] = False
    return mask


class DenoiseBackendTests:
    """Mix-in of conformance tests for a :class:`persona.plugins.kinds.DenoiseBackend`."""

    backend: ClassVar = None
    #: largest change allowed to a constant field on the mask, as a share of its value: an iterative backend
    #: stops at its own tolerance, and one that inpaints a hole starts the hole from elsewhere (the built-in
    #: Huber-ROF and TV, 300 iterations at tol 1e-3: 0.3 %)
    constant_tolerance: ClassVar[float] = 0.01
    #: the noisy step's RMSE to the clean step may grow by at most this factor
    noise_tolerance: ClassVar[float] = 1.0 + 1e-9

    def denoise(self, f, mask=None) -> np.ndarray:
        u = self.backend.denoise(f, mask)
        assert isinstance(u, np.ndarray), f"denoise() returned {type(u).__name__}, not an ndarray"
        assert u.shape == np.shape(f), f"denoise() shape {u.shape}, expected {np.shape(f)}"
        assert u.dtype == np.float64, f"denoise() dtype {u.dtype}, expected float64"
        return u

    def test_is_a_denoise_backend(self):
        from persona.plugins.kinds import DenoiseBackend

        assert isinstance(self.backend, DenoiseBackend)
        for name, field in type(self.backend).Params.model_fields.items():
            assert field.description, f"parameter {name} has no description"

    def test_values_off_the_mask_do_not_change_the_result_on_it(self):
        _, noisy = noisy_step(seed=2)
        mask = with_a_hole(noisy.shape)
        other = noisy.copy()
        other[~mask] = 1e6
        other[np.argwhere(~mask)[0][0], np.argwhere(~mask)[0][1]] = np.nan
        a, b = self.denoise(noisy, mask), self.denoise(other, mask)
        assert np.array_equal(a[mask], b[mask])

    def test_leaves_its_inputs_alone_and_repeats_itself(self):
        _, noisy = noisy_step(seed=4)
        mask = with_a_hole(noisy.shape)
        f, m = noisy.copy(), mask.copy()
        first = self.denoise(f, m)
        assert np.array_equal(f, noisy) and np.array_equal(m, mask)
        assert np.array_equal(first, self.denoise(f, m), equal_nan=True)

    def test_a_constant_field_stays_constant(self):
        f = np.full((32, 40), 3.25)
        mask = with_a_hole(f.shape)
        assert np.abs(self.denoise(f) - 3.25).max() <= self.constant_tolerance * 3.25
        assert np.abs(self.denoise(f, mask)[mask] - 3.25).max() <= self.constant_tolerance * 3.25

    def test_a_noisy_step_ends_no_further_from_the_clean_one(self):
        clean, noisy = noisy_step(seed=1)
        before = np.sqrt(np.mean((noisy - clean) ** 2))
        after = np.sqrt(np.mean((self.denoise(noisy) - clean) ** 2))
        assert after <= before * self.noise_tolerance, (before, after)

    def test_malformed_inputs_are_refused(self):
        with pytest.raises(ValueError):
            self.backend.denoise(np.zeros((4, 4, 3)))
        with pytest.raises(ValueError):
            self.backend.denoise(np.zeros(4))
        with pytest.raises(ValueError):
            self.backend.denoise(np.zeros((4, 4)), np.ones((4, 5), bool))
        with pytest.raises(TypeError):
            self.backend.denoise(np.zeros((4, 4)), np.ones((4, 4)))
