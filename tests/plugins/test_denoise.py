"""Kind ``denoise`` (ALGORITHMS §11): Huber-ROF by Chambolle-Pock, plain TV, identity. Every registered
denoise backend also runs the conformance kit (plugins/denoise_conformance.py)."""

import numpy as np
import pytest
import scipy.optimize
from scipy.ndimage import gaussian_filter
from pydantic import ValidationError

from persona.plugins.builtin.denoise import (
    HuberROFDenoise,
    NoDenoise,
    TVDenoise,
    chambolle_pock_rof,
    rof_energy,
)
from persona.plugins.denoise_conformance import DenoiseBackendTests, noisy_step
from persona.plugins.kinds import DenoiseBackend
from persona.plugins.manager import default_registry


def _conformance(name: str) -> type:
    """The conformance kit's tests on the registered denoise backend ``name`` at its defaults."""
    return type(f"TestConformance_{name}", (DenoiseBackendTests,),
                {"backend": default_registry().get("denoise", name)()})


for _name in default_registry().names("denoise"):  # whatever is registered, built-in or not
    globals()[f"TestConformance_{_name}"] = _conformance(_name)


class TestExcludeConformance(DenoiseBackendTests):
    backend = HuberROFDenoise({"outside": "exclude"})


def _energy_and_gradient(u_flat, f, m, ex, ey, weight, eps):
    """E (the module docstring of denoise.py) and its gradient, written independently of the
    backend: ∇ forward differences on the edges ex / ey, H_ε'(g) = g/ε (|g| <= ε) or g/|g|."""
    u = u_flat.reshape(f.shape)
    gx = np.zeros_like(u)
    gy = np.zeros_like(u)
    gx[:, :-1] = u[:, 1:] - u[:, :-1]
    gy[:-1, :] = u[1:, :] - u[:-1, :]
    gx *= ex
    gy *= ey
    t = np.hypot(gx, gy)
    quad = t <= eps
    energy = weight * np.where(quad, t * t / (2 * eps), t - eps / 2).sum() + 0.5 * (m * (u - f) ** 2).sum()
    scale = np.where(quad, 1 / eps, 1 / np.where(quad, 1.0, t))
    px, py = weight * scale * gx, weight * scale * gy
    grad = m * (u - f)
    # ∇ᵀp: the adjoint of the forward differences
    grad[:, :-1] -= px[:, :-1]
    grad[:, 1:] += px[:, :-1]
    grad[:-1, :] -= py[:-1, :]
    grad[1:, :] += py[:-1, :]
    return energy, grad.ravel()


def _small_problem():
    rng = np.random.default_rng(3)
    f = np.round(rng.normal(0.0, 1.0, (9, 11)) + np.where(np.arange(11) > 5, 2.0, 0.0), 1)
    mask = np.ones(f.shape, bool)
    mask[3:6, 2:4] = False  # a hole to inpaint
    mask[:, 8] = False  # a column that splits the mask (for 'exclude')
    return f, mask


@pytest.mark.parametrize("outside", ["inpaint", "exclude"])
def test_huber_rof_reaches_the_lbfgs_energy(outside):
    """Chambolle-Pock and L-BFGS on the same exact energy agree (ALGORITHMS §15 asks 1e-6 relative;
    measured 6e-16, tested 1e-9),
    and their minimisers agree on the data pixels (where the energy is strictly convex)."""
    f, mask = _small_problem()
    weight, eps = 1.0, 0.05
    u_cp, _ = chambolle_pock_rof(f, mask, weight=weight, epsilon=eps, iterations=20000, tol=0.0,
                                 outside=outside, dtype=np.float64)
    m = mask.astype(float)
    domain = mask if outside == "exclude" else np.ones_like(mask)
    ex = np.zeros(f.shape)
    ey = np.zeros(f.shape)
    ex[:, :-1] = domain[:, :-1] & domain[:, 1:]
    ey[:-1, :] = domain[:-1, :] & domain[1:, :]
    res = scipy.optimize.minimize(_energy_and_gradient, np.where(mask, f, 0.0).ravel(), jac=True,
                                  args=(np.where(mask, f, 0.0), m, ex, ey, weight, eps), method="L-BFGS-B",
                                  options=dict(maxiter=50000, maxcor=30, ftol=1e-16, gtol=1e-11))
    e_lbfgs = res.fun
    e_cp = rof_energy(u_cp, f, mask, weight=weight, epsilon=eps, outside=outside)
    assert e_cp == pytest.approx(_energy_and_gradient(u_cp.ravel(), np.where(mask, f, 0.0), m, ex, ey,
                                                      weight, eps)[0], rel=1e-12)
    assert abs(e_cp - e_lbfgs) <= 1e-9 * e_lbfgs, (e_cp, e_lbfgs)  # measured 6e-16
    assert e_cp < rof_energy(f, f, mask, weight=weight, epsilon=eps, outside=outside)
    assert np.abs(u_cp - res.x.reshape(f.shape))[mask].max() < 1e-5  # measured 7e-8


def test_float32_is_close_to_float64():
    f, mask = _small_problem()
    u64, _ = chambolle_pock_rof(f, mask, iterations=3000, dtype=np.float64)
    u32, _ = chambolle_pock_rof(f, mask, iterations=3000, dtype=np.float32)
    assert np.abs(u64 - u32).max() < 1e-4
    e64, e32 = rof_energy(u64, f, mask), rof_energy(u32, f, mask)
    assert abs(e32 - e64) < 1e-5 * e64


def _noisy_step(seed=0):
    return noisy_step(seed, shape=(64, 64))


def test_huber_rof_restores_a_noisy_step_with_a_sharp_edge():
    """ALGORITHMS §11.3: RMSE 0.50 -> 0.06 on a noisy step; the edge stays a step (no blur)."""
    clean, noisy = _noisy_step()
    u = HuberROFDenoise({"tol": 0.0}).denoise(noisy)
    rmse_in = np.sqrt(np.mean((noisy - clean) ** 2))
    rmse_out = np.sqrt(np.mean((u - clean) ** 2))
    assert rmse_in == pytest.approx(0.5, abs=0.02)
    assert rmse_out < 0.1  # measured 0.076
    # the best Gaussian blur (σ = 1.5) only gets to 0.176: it must trade noise against the edge
    best_blur = min(np.sqrt(np.mean((gaussian_filter(noisy, s, mode="nearest") - clean) ** 2))
                    for s in (0.5, 1.0, 1.5, 2.0, 3.0))
    assert rmse_out < 0.5 * best_blur
    c = clean.shape[1] // 2
    profile = u.mean(axis=0)
    # three quarters of the step happen between two pixels (measured 1.51 of 2); the rest is
    # ROF's contrast loss, a gentle ramp over a few px on each side
    assert profile[c] - profile[c - 1] > 0.7 * 2.0
    rise = np.flatnonzero((profile > 0.2) & (profile < 1.8))  # 10-90 % of the step
    assert len(rise) <= 2, profile[c - 4:c + 4]


def test_tv_and_none_and_the_huber_limit():
    clean, noisy = _noisy_step(seed=1)
    none = NoDenoise().denoise(noisy)
    assert none.dtype == np.float64 and np.array_equal(none, noisy)
    tv = TVDenoise({"tol": 0.0, "iterations": 2000}).denoise(noisy)
    assert np.sqrt(np.mean((tv - noisy) ** 2)) > 0.3  # TV removes most of the 0.5 noise
    huber = HuberROFDenoise({"tol": 0.0, "iterations": 2000}).denoise(noisy)
    assert np.abs(tv - huber).max() > 0.01  # ε = 0.05 is not TV ...
    tiny = HuberROFDenoise({"tol": 0.0, "iterations": 2000, "epsilon": 1e-4}).denoise(noisy)
    # ... but TV is its ε -> 0 limit (ALGORITHMS §11.6)
    assert np.abs(tv - tiny).max() < 0.2 * np.abs(tv - huber).max()
    # TV staircases flat noise into plateaus, Huber keeps it smooth: fewer tiny gradients for TV
    flat_tv, flat_hu = np.abs(np.diff(tv[:, :24], axis=1)), np.abs(np.diff(huber[:, :24], axis=1))
    assert (flat_tv < 1e-3).mean() > (flat_hu < 1e-3).mean() + 0.2


def test_inpaint_fills_the_hole_and_exclude_returns_it():
    clean, noisy = _noisy_step(seed=2)
    mask = np.ones(noisy.shape, bool)
    mask[20:30, 10:50] = False
    other = noisy.copy()
    other[~mask] = 1e6
    other[25, 30] = np.nan  # that they change nothing on the mask is the conformance kit's
    # inpainting fills the hole from its neighbours: values within the data's range, near the step
    u = HuberROFDenoise({"tol": 0.0}).denoise(other, mask)
    assert np.all(np.isfinite(u))
    assert np.abs(u[20:30, 10:28] - 0.0).max() < 0.3 and np.abs(u[20:30, 36:50] - 2.0).max() < 0.3
    # 'exclude' returns the given values off the mask
    u = HuberROFDenoise({"outside": "exclude"}).denoise(other, mask)
    assert np.array_equal(u[~mask], other[~mask], equal_nan=True)


def test_exclude_separates_parts_of_the_mask_and_inpaint_couples_them():
    f = np.zeros((20, 21))
    f[:, 11:] = 5.0
    mask = np.ones(f.shape, bool)
    mask[:, 10] = False  # two parts, 0 and 5, with a gap column between them
    u_ex = HuberROFDenoise({"outside": "exclude", "tol": 0.0}).denoise(f, mask)
    assert np.abs(u_ex - f)[mask].max() < 1e-6
    u_in = HuberROFDenoise({"outside": "inpaint", "tol": 0.0, "precision": "float64",
                            "iterations": 5000}).denoise(f, mask)
    # across the inpainted column the jump costs TV: ROF gives up contrast, w / width per side
    assert u_in[:, :10].mean() == pytest.approx(0.1, abs=0.01)
    assert u_in[:, 11:].mean() == pytest.approx(4.9, abs=0.01)


def test_non_finite_values_are_missing_data():
    clean, noisy = _noisy_step(seed=3)
    holes = noisy.copy()
    holes[5:8, 5:8] = np.nan
    holes[40, 50] = np.inf
    u = HuberROFDenoise().denoise(holes)
    assert np.all(np.isfinite(u))
    assert np.abs(u[5:8, 5:8]).max() < 0.3


def test_registered_with_huber_rof_as_default():
    registry = default_registry()
    assert {"huber_rof", "none", "tv"} <= set(registry.names("denoise"))
    assert registry.default("denoise") == "huber_rof"
    cls = registry.get("denoise", "huber_rof")
    assert issubclass(cls, DenoiseBackend)
    p = cls().params
    assert (p.weight, p.epsilon) == (1.0, 0.05)  # the paper's values


def test_params_are_validated():
    with pytest.raises(ValidationError):
        HuberROFDenoise({"tau": 0.5, "sigma": 0.5})  # τσ > 1/8 may diverge
    with pytest.raises(ValidationError):
        HuberROFDenoise({"epsilon": 0.0})  # that is the tv backend
    with pytest.raises(ValidationError):
        TVDenoise({"epsilon": 0.05})  # unknown key
    with pytest.raises(ValidationError):
        HuberROFDenoise({"outside": "crop"})
    with pytest.raises(ValidationError):
        HuberROFDenoise({"weight": -1})


class _Smearing(DenoiseBackend):
    """Wrong on purpose: a float32 blur of everything, the values off the mask included."""
    name, description = "smearing", "a denoiser that breaks the contract"

    def denoise(self, f, mask=None):
        return gaussian_filter(np.nan_to_num(np.asarray(f, np.float64)), 1.0).astype(np.float32)


def test_the_conformance_kit_can_fail():
    kit = type("Kit", (DenoiseBackendTests,), {"backend": _Smearing()})()
    for check in (kit.test_values_off_the_mask_do_not_change_the_result_on_it,
                  kit.test_a_constant_field_stays_constant, kit.test_malformed_inputs_are_refused):
        with pytest.raises((AssertionError, pytest.fail.Exception)):
            check()
