"""Multi-scale expression-dependent blending (paper Eq. 3, ALGORITHMS §12.3-§12.4, §12.7)."""

import cv2
import numpy as np
import pytest

from persona.plugins.face.blend import (BlendCache, BlendSums, collapse, expression_weights, gaussian_pyramid,
                                        given_back, laplacian_pyramid, level_bias, photos_drawn, widened)

H, W = 244, 194


def _texture(rng, shape=(H, W, 3)):
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.5) * 255


@pytest.mark.parametrize("levels", [3, 5, 7])
def test_laplacian_pyramid_reconstructs_exactly_with_odd_sizes(levels):
    image = _texture(np.random.default_rng(0))
    pyramid = laplacian_pyramid(image, levels)
    assert [p.shape[:2] for p in pyramid][:5] == [(244, 194), (122, 97), (61, 49), (31, 25), (16, 13)][:levels]
    assert np.abs(collapse(pyramid) - image).max() < 1e-3  # float32 rounding on 0-255 values


def test_level_bias_is_infinite_only_at_the_coarsest_level():
    bias = level_bias(5, beta=20, tau=1)
    assert np.isinf(bias[-1]) and np.isfinite(bias[:-1]).all()
    assert bias[-2] == 1.0 and bias[-3] == pytest.approx(2.0 ** -20)  # l = 1, l = 2
    assert (level_bias(5, beta=20, tau=0) == 0).all()  # no uniform term, not even a NaN at l = 0


def test_expression_weights_follow_the_paper_and_relative_ones_never_vanish():
    target = np.zeros((49, 2))
    fid = np.stack([target + 2.0, target + 40.0])  # 2 px and 40 px per coordinate
    e = expression_weights(fid, target, sigma=10)
    assert e[0] == pytest.approx(np.exp(-98 * 4 / 200))  # 0.14, ALGORITHMS §12.3
    assert e[1] == 0.0  # underflows
    r = expression_weights(fid, target, sigma=10, relative=True)
    assert r[0] == 1.0 and 0 <= r[1] < 1


def test_photos_drawn_counts_equal_weights_and_one_photo():
    assert photos_drawn(np.ones(7)) == pytest.approx(7)
    assert photos_drawn(np.array([0.0, 3.0, 0.0])) == pytest.approx(1)
    assert photos_drawn(np.array([1.0, 1.0, 0.0, 0.0])) == pytest.approx(2)


def test_a_rare_expression_is_drawn_from_at_least_min_photos():
    """Three photos near the target, 47 far: σ 10 draws on about 3; ``min_photos`` 20 widens σ until the
    weights draw on 20 (to 0.1 %), the nearest photos still weighing most. A target many photos are near
    keeps σ; asking for more photos than there are gives them all, about equally."""
    rng = np.random.default_rng(3)
    target = np.zeros((49, 2))
    near = target + rng.normal(0, 0.5, (3, 49, 2))
    far = target + 8 + rng.normal(0, 2, (47, 49, 2))
    fid = np.concatenate([near, far])
    assert photos_drawn(expression_weights(fid, target, sigma=10)) == pytest.approx(3, abs=0.1)
    wide = expression_weights(fid, target, sigma=10, min_photos=20)
    assert photos_drawn(wide) == pytest.approx(20, rel=1e-3)
    assert wide[:3].min() > wide[3:].max()
    crowd = far.mean(axis=0)
    np.testing.assert_array_equal(expression_weights(far, crowd, sigma=10, min_photos=20),
                                  expression_weights(far, crowd, sigma=10))
    d2 = np.array([0.0, 1.0, 4.0, np.inf])
    assert photos_drawn(np.exp(-d2[:3] / (2 * widened(d2, 0.1, 10) ** 2))) == pytest.approx(3, rel=1e-3)


def _collection(rng, n=6):
    images = np.stack([_texture(rng) for _ in range(n)])
    valid = np.ones((n, H, W), bool)
    valid[0, :40] = False  # one photo misses the top rows
    return images, valid


def test_weights_sum_to_one_at_every_level_and_nothing_is_nan():
    rng = np.random.default_rng(1)
    images, valid = _collection(rng)
    cache = BlendCache.build(images, valid, levels=5, alpha=1, beta=20, tau=1)
    for e in (rng.random(6), np.zeros(6), np.array([1.0, 0, 0, 0, 0, 0])):
        weights = cache.weights(e)
        for k, w in enumerate(weights):
            assert np.isfinite(w).all()
            np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-5, err_msg=f"level {k}")
        out = cache.blend(e)
        assert np.isfinite(out).all()
        # the blend is the normalised weighted sum of the Laplacian levels
        filled = images.copy()  # unseen pixels take the mean of the photos that see them
        filled[0, :40] = images[1:, :40].mean(axis=0)
        bands = [np.stack(b) for b in zip(*(laplacian_pyramid(im, 5) for im in filled))]
        expected = collapse([np.einsum("nhw,nhwc->hwc", w, b) for w, b in zip(weights, bands)])
        np.testing.assert_allclose(out, expected, atol=1e-2)
    # the photo missing the top rows has no weight there at the finest level
    assert cache.weights(np.ones(6))[0][0, :38].max() == 0


def test_coarse_band_is_the_mean_and_fine_detail_comes_from_the_target_photos():
    """All photos share their detail up to the coarse-band lighting (ALGORITHMS §12.7 test 1),
    except two that carry a fine pattern: the low frequencies are the collection's mean
    whatever the target, the pattern appears only when those photos have the weight."""
    rng = np.random.default_rng(2)
    base = cv2.GaussianBlur(_texture(rng), (0, 0), 4) * 4 - 2 * 127  # smooth, full range
    n = 8
    gains = rng.uniform(0.85, 1.15, (n, 1, 1, 3)).astype(np.float32)
    images = np.repeat(base[None], n, axis=0) * gains  # colour casts: ±15 %
    stripes = (8 * np.sign(np.sin(np.arange(W) * np.pi / 2))).astype(np.float32)[None, :, None]
    images[:2] += stripes  # 4-px period: only in the finest band
    cache = BlendCache.build(images, np.ones((n, H, W), bool), levels=5, alpha=0, beta=20, tau=1)
    smile = cache.blend(np.r_[1.0, 1.0, np.zeros(n - 2)])
    neutral = cache.blend(np.r_[0.0, 0.0, np.ones(n - 2)])

    def low(img):
        return gaussian_pyramid(img, 5)[-1]

    def stripe_amplitude(img):
        residual = img - cv2.GaussianBlur(img, (0, 0), 3)
        return np.abs(np.mean(residual * np.sign(stripes), axis=(0, 2))).mean()

    mean_low = low(images.mean(axis=0))
    for out in (smile, neutral):  # α = 0: uniform weights at the coarsest level
        np.testing.assert_allclose(low(out), mean_low, atol=1.0)  # of 0-255 (pyrDown∘pyrUp is not exact)
    assert stripe_amplitude(smile) > 0.6 * 8 > 10 * stripe_amplitude(neutral)
    # τ = 0: no uniform term, so even the coarsest level comes from the chosen photos
    chosen = BlendCache.build(images, np.ones((n, H, W), bool), levels=5, alpha=0, beta=20, tau=0).blend(
        np.r_[1.0, 1.0, np.zeros(n - 2)])
    assert np.isfinite(chosen).all()
    np.testing.assert_allclose(low(chosen), low(images[:2].mean(axis=0)), atol=1.0)


def test_confidence_takes_a_photo_out_where_it_failed_to_register():
    """A photo whose alignment confidence is 0 in a region has no weight there at the fine
    levels, however sharp it is (a tear has a strong Laplacian); the weights still sum to 1."""
    rng = np.random.default_rng(3)
    images, valid = _collection(rng)
    images[0, 100:140, 60:120] += 60 * np.sign(np.sin(np.arange(60) * np.pi / 3))[None, :, None]  # sharp "tear"
    confidence = np.ones((6, H, W), np.float32)
    confidence[0, 90:150, 50:130] = 0
    e = np.r_[1.0, 0.2, 0.2, 0.2, 0.2, 0.2]
    plain = BlendCache.build(images, valid, levels=5, alpha=1, beta=20, tau=1).weights(e)
    trusted = BlendCache.build(images, valid, levels=5, alpha=1, beta=20, tau=1, confidence=confidence).weights(e)
    assert plain[0][0, 110:130, 70:110].mean() > 0.5  # without it, the tear dominates the finest level
    assert trusted[0][0, 100:140, 60:120].max() < 1e-6
    for w in trusted:
        np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-5)
    np.testing.assert_allclose(trusted[0][0, 200:, :], plain[0][0, 200:, :], atol=1e-5)  # untouched elsewhere


def _grainy_photos(n=8, h=96, w=80):
    """n photos of one shared face (a smooth ramp and a sharp dark bar at x 39-41, in every photo),
    each with its own fine grain (skin that does not coincide), and their cache (4 levels, α 0)."""
    rng = np.random.default_rng(3)
    xs = np.mgrid[0:h, 0:w][1]
    shared = 100 + 0.5 * xs + 60.0 * ((xs > 38) & (xs < 42))
    grain = [cv2.GaussianBlur(rng.normal(0, 12, (h, w)).astype(np.float32), (0, 0), 0.7) for _ in range(n)]
    images = np.stack([np.repeat((shared + g)[..., None], 3, axis=2) for g in grain]).astype(np.float32)
    return images, BlendCache.build(images, np.ones((n, h, w), bool), levels=4, alpha=0.0, beta=20, tau=1)


def test_held_detail_is_the_held_targets_band_in_every_image():
    """Two targets that draw on different grainy photos, and a third (the neutral) on all of them: with
    ``held`` the third, each target's image is its plain blend plus (g_k - 1) × the neutral's level k, to
    float precision, the same added to both, so the two differ exactly as their plain blends do; without
    it, by their difference times the gains."""
    images, cache = _grainy_photos()
    weights = np.zeros((3, len(images)), np.float32)
    weights[0, :4], weights[1, 4:], weights[2] = 1, 1, 1
    sums = BlendSums.zeros(3, cache.totals)
    sums.add(cache.weighted, cache.detail, weights)
    gains = sums.detail_gains(cache.totals, 1.0, 2)
    assert all(g > 1.05 for g in gains)
    plain = sums.finish(cache.totals)
    held = sums.finish(cache.totals, gains=gains, rows=[0, 1], held=2)
    extra = collapse([np.float32(g - 1) * sums.band(cache.totals, k, 2)[0] for k, g in enumerate(gains)]
                     + [np.zeros_like(sums.band(cache.totals, k, 2)[0]) for k in range(len(gains), cache.levels)])
    np.testing.assert_allclose(held, plain[:2] + extra[None], atol=1e-3)
    np.testing.assert_allclose(held[0] - held[1], plain[0] - plain[1], atol=1e-3)
    scaled = sums.finish(cache.totals, gains=gains, rows=[0, 1])
    assert np.abs((scaled[0] - scaled[1]) - (plain[0] - plain[1])).max() > 1.0


def test_given_back_is_a_share_of_the_energy_the_blend_lost():
    """A band of amplitude 2 (energy 4) where one photo has energy 10: share 0 keeps it, share 1 gives
    it the photo's 10, share 0.5 half of what it lost (7); a band that lost nothing is kept."""
    band, seen = np.full((6, 5, 3), 2.0, np.float32), np.ones((6, 5), bool)
    energy = lambda s: 4 * given_back(band, seen, 10.0, s) ** 2  # noqa: E731
    assert energy(0.0) == pytest.approx(4) and energy(1.0) == pytest.approx(10) and energy(0.5) == pytest.approx(7)
    assert given_back(band, seen, 3.0, 1.0) == 1.0 and given_back(band * 0, seen, 3.0, 1.0) == 1.0


def test_detail_share_gives_back_a_share_of_the_fine_energy(monkeypatch):
    """The grainy photos' blend with ``share`` s: each fine band is the plain blend's times one factor
    (the shared bar sharpened as much as the grain), so that its mean energy is e + s (E - e) of the
    plain band's e and a photo's E; the two coarsest bands, and every band at share 0, are as they were."""
    import persona.plugins.face.blend as blend_module
    images, cache = _grainy_photos()
    e = np.ones(len(images))
    pyramids = []
    monkeypatch.setattr(blend_module, "collapse", lambda pyramid: pyramids.append(pyramid) or collapse(pyramid))
    plain = cache.blend(e)
    assert np.array_equal(cache.blend(e, share=0.0), plain)
    photo = [np.mean([np.mean(laplacian_pyramid(image, cache.levels)[k] ** 2) for image in images])
             for k in range(cache.levels)]
    for s in (0.5, 1.0):
        cache.blend(e, share=s)
        before, after = pyramids[0], pyramids[-1]
        for k in range(cache.levels - 2):
            have = np.mean(before[k] ** 2)
            assert have < 0.9 * photo[k]  # the mean of eight lost some of it
            assert np.mean(after[k] ** 2) == pytest.approx(have + s * (photo[k] - have), rel=1e-4), (s, k)
            factor = after[k][np.abs(before[k]) > 0.1] / before[k][np.abs(before[k]) > 0.1]
            assert np.ptp(factor) < 1e-4 * factor.mean()  # one factor for the whole band
        for k in range(cache.levels - 2, cache.levels):
            np.testing.assert_array_equal(after[k], before[k])
