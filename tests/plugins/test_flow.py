"""The built-in flow backends: the conformance suite for each, and Liu-specific details."""

import math

import numpy as np
import pytest
from persona.plugins.builtin import flow as F
from persona.plugins.flow_conformance import (
    FACE_SHAPE,
    FlowBackendTests,
    end_point_error,
    textured_image,
    warped_pair,
)
from persona.plugins.kinds import FlowBackend
from persona.plugins.manager import default_registry
from pydantic import ValidationError


class TestLiu(FlowBackendTests):
    backend = F.LiuFlow()


class TestDis(FlowBackendTests):
    backend = F.DISFlow()


class TestTVL1(FlowBackendTests):
    backend = F.TVL1Flow()
    # brightness constancy only (L1 on grey intensities): a global offset drives the flow away
    handles_brightness = False


class TestDeepFlow(FlowBackendTests):
    backend = F.DeepFlow()


class TestFarneback(FlowBackendTests):
    backend = F.FarnebackFlow()


class TestVarRef(FlowBackendTests):
    backend = F.VariationalRefinementFlow()


# -- registration ----------------------------------------------------------------------------


def test_all_registered_with_one_default():
    registry = default_registry()
    names = registry.names("flow")
    assert set(names) == {"liu", "dis", "tvl1", "deepflow", "farneback", "varref"}
    assert sum(registry.get("flow", n).default for n in names) <= 1
    for n in names:
        cls = registry.get("flow", n)
        assert issubclass(cls, FlowBackend)
        for field, info in cls.Params.model_fields.items():
            assert info.description, f"{n}.{field} has no description"


def test_flow_plugin_imports_no_dask_or_zarr():
    import subprocess
    import sys

    code = ("import sys; import persona.plugins.builtin.flow, persona.plugins.flow_conformance; "
            "bad = [m for m in ('dask', 'zarr', 'distributed', 'persona.dag', 'persona.stores') "
            "if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stdout + out.stderr


# -- Liu specifics ---------------------------------------------------------------------------


def test_liu_level_count():
    # ALGORITHMS §6.2: width 194, ratio 0.85, minWidth 20 -> 13 levels, coarsest 27.6 px wide
    assert F.pyramid_levels(194, 0.85, 20) == 13
    assert F.pyramid_levels(10, 0.85, 20) == 1
    pyr = F._pyramid(np.zeros((1, 244, 194)), 0.85, 13)
    assert len(pyr) == 13
    assert [p.shape[2] for p in pyr][:3] == [194, int(194 * 0.85), int(194 * 0.85 ** 2)]
    assert abs(pyr[-1].shape[2] - 194 * 0.85 ** 12) < 1.5  # 27.6 px


def test_liu_defaults_are_the_papers():
    p = F.LiuFlow().params
    assert (p.alpha, p.ratio, p.min_width, p.outer, p.inner, p.sor) == (0.02, 0.85, 20, 4, 1, 40)


@pytest.mark.parametrize("bad", [{"ratio": 1.0}, {"ratio": 0.0}, {"ratio": 1.2}, {"alpha": 0},
                                 {"sor": 0}, {"alpha_": 0.3}, {"minWidth": 20}])
def test_liu_params_validation(bad):
    with pytest.raises(ValidationError):
        F.LiuFlow(bad)


def test_params_reject_unknown_keys_for_every_backend():
    for cls in F.BACKENDS:
        with pytest.raises(ValidationError, match="Extra inputs"):
            cls({"no_such_parameter": 1})


def test_tvl1_lambda_by_name():
    assert F.TVL1Flow({"lambda": 0.3}).params.lambda_ == 0.3


def _liu_sor_reference(phi, a11, a12, a22, b1, b2, alpha, n_sor):
    """Literal transcription of the SOR loop of Liu's OpticalFlow::SmoothFlowSOR."""
    h, w = phi.shape
    du = np.zeros((h, w))
    dv = np.zeros((h, w))
    omega = 1.8
    for _ in range(n_sor):
        for i in range(h):
            for j in range(w):
                s1 = s2 = coeff = 0.0
                if j > 0:
                    s1 += phi[i, j - 1] * du[i, j - 1]
                    s2 += phi[i, j - 1] * dv[i, j - 1]
                    coeff += phi[i, j - 1]
                if j < w - 1:
                    s1 += phi[i, j] * du[i, j + 1]
                    s2 += phi[i, j] * dv[i, j + 1]
                    coeff += phi[i, j]
                if i > 0:
                    s1 += phi[i - 1, j] * du[i - 1, j]
                    s2 += phi[i - 1, j] * dv[i - 1, j]
                    coeff += phi[i - 1, j]
                if i < h - 1:
                    s1 += phi[i, j] * du[i + 1, j]
                    s2 += phi[i, j] * dv[i + 1, j]
                    coeff += phi[i, j]
                s1 *= -alpha
                s2 *= -alpha
                coeff *= alpha
                s1 += a12[i, j] * dv[i, j]
                du[i, j] = (1 - omega) * du[i, j] + omega / (a11[i, j] + alpha * 0.05 + coeff) * (b1[i, j] - s1)
                s2 += a12[i, j] * du[i, j]
                dv[i, j] = (1 - omega) * dv[i, j] + omega / (a22[i, j] + alpha * 0.05 + coeff) * (b2[i, j] - s2)
    return du, dv


def test_liu_sor_matches_liu_loop():
    rng = np.random.default_rng(0)
    h, w = 7, 9
    phi = rng.uniform(1, 50, (h, w))
    a11, a22 = rng.uniform(0, 2, (2, h, w))
    a12 = rng.uniform(-0.5, 0.5, (h, w))
    b1, b2 = rng.normal(0, 1, (2, h, w))
    coef = np.zeros((h, w, 12))
    duv = np.zeros((h + 2, w + 2, 2))
    F._sor(phi, a11, a12, a22, b1, b2, 0.02, 1.8, 5, coef, duv)
    du, dv = _liu_sor_reference(phi, a11, a12, a22, b1, b2, 0.02, 5)
    np.testing.assert_allclose(duv[1:-1, 1:-1, 0], du, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(duv[1:-1, 1:-1, 1], dv, rtol=1e-9, atol=1e-12)


def test_liu_feature_channels():
    im = textured_image((20, 30), seed=1).transpose(2, 0, 1).copy()
    feat = F._im2feature(im, F._DERIV5)
    assert feat.shape == (5, 20, 30)
    grey = im[0] * 0.299 + im[1] * 0.587 + im[2] * 0.114
    np.testing.assert_allclose(feat[0], grey)
    # [1, -8, 0, 8, -1] / 12 derivative, interior
    ref = (grey[:, 0:-4] - 8 * grey[:, 1:-3] + 8 * grey[:, 3:-1] - grey[:, 4:]) / 12
    np.testing.assert_allclose(feat[1][:, 2:-2], ref)
    np.testing.assert_allclose(feat[3], im[1] - im[0])
    np.testing.assert_allclose(feat[4], im[1] - im[2])
    assert F._im2feature(im[:1].copy(), F._DERIV5).shape == (3, 20, 30)


def test_liu_alpha_changes_smoothness():
    i0, i1, truth = warped_pair((122, 97), seed=11)
    rough = F.LiuFlow({"alpha": 0.005}).flow(i0, i1)
    smooth = F.LiuFlow({"alpha": 0.3}).flow(i0, i1)

    def tv(w):
        return float(np.abs(np.diff(w, axis=0)).mean() + np.abs(np.diff(w, axis=1)).mean())

    assert tv(smooth) < tv(rough)
    assert end_point_error(smooth, truth) < 1.0  # alpha = 0.3 over-smooths (ALGORITHMS §6.3)


def test_liu_image0_outside_mode_runs():
    i0, i1, truth = warped_pair((122, 97), seed=12)
    w = F.LiuFlow({"outside": "image0"}).flow(i0, i1)
    assert end_point_error(w, truth) < 0.2


def test_larger_displacement_liu():
    """The pyramid recovers ~8 px motions on the face-sized pair."""
    i0, i1, truth = warped_pair(FACE_SHAPE, seed=13, max_norm=8.0)
    w = F.LiuFlow().flow(i0, i1)
    assert end_point_error(w, truth, border=16) < 0.3


def test_fill_outside_mask_is_smooth_and_keeps_inside():
    img = textured_image((60, 50), seed=3)
    mask = np.zeros((60, 50), bool)
    mask[10:40, 15:35] = True
    out = F.fill_outside_mask(img, mask)
    np.testing.assert_array_equal(out[mask], img[mask])
    assert np.all(np.isfinite(out))
    # no step at the mask edge bigger than the texture's own variation
    assert np.abs(np.diff(out, axis=1)).max() < 2 * np.abs(np.diff(img, axis=1)).max()


def test_prepare_pair_messages():
    a = np.zeros((20, 20))
    with pytest.raises(ValueError, match="same shape"):
        F.prepare_pair(a, np.zeros((20, 21)))
    with pytest.raises(ValueError, match="dtype"):
        F.prepare_pair(a.astype(np.int32), a.astype(np.int32))
    with pytest.raises(ValueError, match="NaN"):
        F.prepare_pair(a + np.nan, a)
    with pytest.raises(ValueError, match=">= 8 px"):
        F.prepare_pair(np.zeros((4, 4)), np.zeros((4, 4)))
    i0, _, m = F.prepare_pair((a * 255).astype(np.uint8), a, a > -1)
    assert i0.dtype == np.float64 and i0.shape == (20, 20, 1) and m.dtype == bool
    assert math.isclose(F.prepare_pair(np.full((9, 9), 255, np.uint8), a[:9, :9])[0].max(), 1.0)


def test_dis_params():
    assert F.DISFlow({"preset": "fast", "finest_scale": None}).params.finest_scale is None
    with pytest.raises(ValidationError, match="patch_stride"):
        F.DISFlow({"patch_size": 4, "patch_stride": 6})
    i0, i1, truth = warped_pair((122, 97), seed=14)
    w = F.DISFlow({"preset": "ultrafast", "patch_size": 6}).flow(i0, i1)  # stride 4 kept
    assert end_point_error(w, truth) < 1.0


def test_liu_without_mask_latches_onto_the_edge():
    """Why the mask exists: Liu's flow runs away when image0 is black outside a face."""
    i0, i1, truth = warped_pair((122, 97), seed=15)
    h, w = 122, 97
    y, x = np.mgrid[0:h, 0:w]
    mask = ((x - w / 2) / (0.42 * w)) ** 2 + ((y - h / 2) / (0.45 * h)) ** 2 <= 1
    i0 = np.where(mask[:, :, None], i0, 0.0)
    backend = F.LiuFlow()
    err_masked = np.linalg.norm((backend.flow(i0, i1, mask) - truth)[mask], axis=-1).mean()
    err_plain = np.linalg.norm((backend.flow(i0, i1) - truth)[mask], axis=-1).mean()
    assert err_masked < 0.2
    assert err_plain > 1.0


@pytest.mark.parametrize("shape", [(8, 8), (8, 200), (200, 8), (12, 9, 3)])
def test_tiny_images(shape):
    rng = np.random.default_rng(0)
    a, b = rng.random(shape), rng.random(shape)
    for cls in F.BACKENDS:
        w = cls().flow(a, b)
        FlowBackendTests.check_contract(w, shape[:2])
