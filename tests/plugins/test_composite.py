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
    face = np.clip(200 + checker(size)[..., None] + np.zeros(3), 0, 255).astype(np.uint8)
    alpha, disk = feathered_disk(size, radius)
    return face, frame, alpha, disk


def checker(size):
    """A 2-px checker of ±15 grey levels: B's fine detail."""
    ys, xs = np.mgrid[0:size, 0:size]
    return ((ys // 2 + xs // 2) % 2) * 30 - 15


def feathered_disk(size, radius):
    """(alpha, disk): a centred disk mask, feathered inwards over 3 px as the renderer's, and the disk."""
    ys, xs = np.mgrid[0:size, 0:size]
    disk = ((ys - size / 2) ** 2 + (xs - size / 2) ** 2 <= radius ** 2).astype(np.float32)
    return cv2.GaussianBlur(disk, (0, 0), 3.0) * disk, disk.astype(bool)


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


def test_paste_and_seam_on_the_masks_box_are_the_whole_frames(monkeypatch):
    """paste and seam work on the mask's box only: the same image and the same figures to the bit as
    on the whole frame, for a face in the middle and one cut by the frame's corner."""
    rng = np.random.default_rng(5)
    face, frame = (rng.integers(0, 256, (90, 120, 3), dtype=np.uint8) for _ in range(2))
    ys, xs = np.mgrid[0:90, 0:120]
    for cy, cx in ((45, 60), (5, 112)):
        alpha = np.clip((30 - np.hypot(ys - cy, xs - cx)) / 3, 0, 1).astype(np.float32)  # feathered 3 px
        boxed = composite.paste(face, frame, alpha), composite.seam(face, frame, alpha)
        with monkeypatch.context() as m:  # the box as the whole frame
            m.setattr(composite, "mask_box", lambda sel, margin=0: (slice(None),) * 2 if np.any(sel) else None)
            whole = composite.paste(face, frame, alpha), composite.seam(face, frame, alpha)
        assert np.array_equal(boxed[0], whole[0]) and boxed[1] == whole[1]
        a = alpha[..., None]
        assert np.array_equal(boxed[0], np.round(face * a + frame * (1 - a)).astype(np.uint8))


def lit_scene(size=200, radius=60):
    """A's frame: A's skin lit from the right (0.7 to 1.3 across the frame); B's face: a lighter skin
    with a checker detail, evenly lit; a disk mask feathered over 3 px."""
    rng = np.random.default_rng(1)
    light = 0.7 + 0.6 * np.arange(size) / size  # along x
    frame = np.clip(np.array([110, 90, 80]) * light[None, :, None] + rng.normal(0, 3, (size, size, 3)), 0, 255)
    face = np.clip(np.array([170, 140, 120]) + checker(size)[..., None], 0, 255)
    return face.astype(np.uint8), frame.astype(np.uint8), feathered_disk(size, radius)[0]


def test_matching_the_light_removes_the_step_and_keeps_the_detail():
    face, frame, alpha = lit_scene()
    assert np.array_equal(composite.blend(face, frame, alpha, lighting=0, hair=0), composite.multiband(face, frame, alpha))
    before = composite.seam(composite.multiband(face, frame, alpha), frame, alpha)
    blended = composite.blend(face, frame, alpha, lighting=1)
    after = composite.seam(blended, frame, alpha)
    print(f"\nmultiband {before}, matched {after}")
    assert before["colour_step"] > 30 and abs(after["colour_step"]) < 2  # measured 45.2 -> 0.0
    # A's light comes with it: the face's left and right edges take the frame's colour there (±4 levels)
    for x in (45, 145):
        assert np.abs(blended[95:105, x:x + 10].mean(axis=(0, 1)) - frame[95:105, x:x + 10].mean(axis=(0, 1))).max() < 4
    # B's detail stays, in proportion to the tone (the checker's contrast over its mean, within 5 %)
    centre, own = blended[80:120, 80:120].astype(float), face[80:120, 80:120].astype(float)
    assert abs(centre.std() / centre.mean() - own.std() / own.mean()) < 0.05 * own.std() / own.mean()


def test_the_drivers_own_pixels_keep_their_colour_where_b_takes_a_light():
    """Pixels the renderer marks as the driver's own (its mouth interior, ``own``) are A's already:
    under a gain that darkens B's lighter face by a third, a white patch of teeth marked own stays
    white (within 2 levels), where unmarked it darkens with the face; the rest of the face is relit as
    before."""
    face, frame, alpha = lit_scene()
    face[110:120, 85:115] = 235  # teeth, in the lower middle of the face
    own = np.zeros(alpha.shape, np.float32)
    own[110:120, 85:115] = 1
    teeth = np.s_[112:118, 88:112]
    relit = composite.blend(face, frame, alpha, hair=0)[teeth].astype(float)
    kept = composite.blend(face, frame, alpha, hair=0, own=own)[teeth].astype(float)
    print(f"\nteeth relit {relit.mean(axis=(0, 1))}, kept {kept.mean(axis=(0, 1))}")
    assert relit.mean() < 200 and np.abs(kept.mean(axis=(0, 1)) - 235).max() <= 2
    rest = alpha > 0  # the face away from the patch is relit as before (the blend's coarse bands spread a little)
    rest[95:135, 70:130] = False
    change = np.abs(composite.blend(face, frame, alpha, hair=0, own=own)[rest].astype(float)
                    - composite.blend(face, frame, alpha, hair=0)[rest])
    assert change.mean() < 0.5 and change.max() <= 3


def test_hair_under_the_edge_does_not_darken_the_face():
    face, frame, alpha = lit_scene()
    clear = composite.match_lighting(face, frame, alpha)
    frame[:80] = (40, 28, 20)  # A's dark brown hair under the top of B's edge
    haired = composite.match_lighting(face, frame, alpha)
    top = np.s_[45:60, 85:115]  # B's forehead, just inside the edge
    change = haired[top].astype(float).mean() / clear[top].astype(float).mean()
    print(f"\nforehead with hair under it / without: {change:.3f}")
    assert change > 0.9  # the hair's colour would scale it by about 0.3
    far = alpha == 0
    assert np.array_equal(haired[far], face[far])  # outside the face nothing changes


def test_tone_zero_keeps_b_mean_tone_and_takes_a_light():
    face, frame, alpha = lit_scene()
    kept = composite.match_lighting(face, frame, alpha, tone=0, tone_reach=0)
    inside = alpha > 0.5
    print(f"\nB's mean tone {face[inside].mean(axis=0)}, kept {kept[inside].mean(axis=0)}")
    assert np.abs(kept[inside].mean(axis=0) - face[inside].mean(axis=0)).max() < 0.05 * face[inside].mean()
    # A's light from the right: B's right edge lighter than its left, as the frame's (ratio 1.22 at x 150/50)
    ratio = kept[95:105, 145:155].mean() / kept[95:105, 45:55].mean()
    assert abs(ratio - frame[95:105, 145:155].mean() / frame[95:105, 45:55].mean()) < 0.1


def test_tone_within_reach_meets_a_at_the_edge_and_keeps_b_in_the_middle():
    """``tone_reach``: B's face takes all of A's tone at its edge (no step, as with ``tone`` 1) and
    ``tone`` of it in its middle: with ``tone`` 0.5 the middle's log colour lies half way between B's
    own tone (``tone`` 0) and A's (``tone`` 1), within 0.03, where a seam with ``tone`` 0 alone steps."""
    face, frame, alpha = lit_scene()
    own, taken = (composite.blend(face, frame, alpha, tone=t, tone_reach=0, hair=0) for t in (0, 1))
    ramped = composite.blend(face, frame, alpha, tone=0.5, tone_reach=0.5, hair=0)
    steps = [composite.seam(img, frame, alpha)["colour_step"] for img in (own, taken, ramped)]
    middle = np.s_[92:108, 92:108]
    log = [np.log1p(img[middle].astype(float).mean(axis=(0, 1))) for img in (own, taken, ramped)]
    print(f"\nsteps B's tone / A's / within reach {np.round(steps, 1)}; middle {[np.round(np.expm1(v)) for v in log]}")
    assert steps[0] > 15 and abs(steps[1]) < 2 and abs(steps[2]) < 2  # measured 46.5 / 0.5 / 1.2
    assert np.abs(log[2] - (log[0] + log[1]) / 2).max() < 0.03


def test_a_fringe_stays_in_front_and_a_collar_does_not():
    face, frame, alpha = lit_scene()  # the disk spans rows 40-160; reach: 12 % of 120 px
    hair = (30, 22, 18)
    frame[:50] = hair  # A's fringe, 10 px into the top of B's face
    frame[152:] = hair  # a dark collar as far into its bottom
    kept, covered = composite.blend(face, frame, alpha), composite.blend(face, frame, alpha, hair=0)
    fringe, collar = np.s_[44:48, 90:110], np.s_[153:157, 90:110]
    print(f"\nfringe: kept {kept[fringe].mean():.1f}, covered {covered[fringe].mean():.1f}; "
          f"collar: {kept[collar].mean():.1f}, {covered[collar].mean():.1f}")
    assert np.abs(kept[fringe].astype(float) - hair).mean() < 15  # A's hair in front of B's forehead
    assert covered[fringe].mean() > 2 * kept[fringe].mean()  # B's face over it, as before
    assert np.abs(kept[collar].astype(float) - covered[collar]).max() <= 2  # below, B's chin stays
    middle = np.s_[70:130, 70:130]
    assert np.abs(kept[middle].astype(float) - covered[middle]).mean() < 1  # B's face itself unchanged
    alone = np.zeros_like(alpha)  # no face, nothing in front
    assert not composite.hair_in_front(face, frame, alone).any()


def test_the_drivers_fringe_stays_in_front_of_the_puppets_own_fringe():
    """B built from one video keeps B's fringe in its texture: B's render is dark hair along its top edge
    too, not skin. A's fringe there is what A's frame shows now, and stays in front as it does over B's
    skin (the map was A's not-skin times B's skin likeness, so B's own hair was drawn over A's)."""
    face, frame, alpha = lit_scene()  # the disk spans rows 40-160; the band: 14 px inside its edge
    hair, own = (30, 22, 18), (200, 170, 80)  # A dark-haired, B blond
    frame[:50] = hair  # A's fringe, 10 px into the top of B's face
    face[:52] = own  # B's own fringe, baked into its texture, as far in and a little further
    kept, covered = composite.blend(face, frame, alpha), composite.blend(face, frame, alpha, hair=0)
    fringe = np.s_[44:48, 90:110]
    print(f"\nover B's own fringe: kept {kept[fringe].mean():.1f}, covered {covered[fringe].mean():.1f}, "
          f"A's hair {np.mean(hair):.1f}")
    assert np.abs(kept[fringe].astype(float) - hair).mean() < 15  # A's hair in front
    assert composite.hair_in_front(face, frame, alpha)[fringe].min() > 0.9


def test_a_blot_inside_the_edge_is_covered_but_a_strand_that_reaches_in_is_kept():
    """Inside B's edge band (14 px wide here) A's frame has a dark blot 6 px across that touches nothing
    beyond B's edge (a mole, stubble or a shadow on A's cheek where A's face is wider than B's): B's face
    covers it, as it covers A's skin. A strand of hair 4 px wide crossing the same band from beyond the
    edge stays in front, as a fringe does."""
    face, frame, alpha = lit_scene()  # the disk spans columns 40-160, rows 40-160
    hair = (30, 22, 18)
    frame[97:103, 148:154] = hair  # the blot: 6-12 px inside the right edge (x 160), not touching it
    frame[96:100, 30:58] = hair  # the strand: from beyond the left edge (x 40) 18 px into the face
    kept, covered = composite.blend(face, frame, alpha), composite.blend(face, frame, alpha, hair=0)
    blot, strand = np.s_[98:102, 149:153], np.s_[97:99, 44:52]
    print(f"\nblot: {kept[blot].mean():.1f} (B's face over it: {covered[blot].mean():.1f}); "
          f"strand: {kept[strand].mean():.1f} (covered: {covered[strand].mean():.1f})")
    assert np.abs(kept[blot].astype(float) - covered[blot]).max() <= 2  # B's face over the blot
    assert covered[strand].mean() > kept[strand].mean() + 40  # the strand in front: darker
    in_front = composite.hair_in_front(face, frame, alpha)
    assert in_front[blot].max() < 0.05 and in_front[strand].min() > 0.5


def test_the_drivers_eye_beside_the_edge_is_not_kept_in_front_but_its_fringe_is():
    """A's eye whose outer corner and lashes (dark, not skin) lie in B's edge band, where A's face is
    narrower than B's: kept in front of B's face as if it were hair without A's landmarks (a smudge
    beside B's eye, seen on Powell driven by the woman), covered by B's face with them (``features_of``:
    the eye's hull grown by half its width sideways); A's fringe across the top is kept either way."""
    face, frame, alpha = lit_scene()  # the disk spans columns 40-160; the band: 14 px inside its edge
    hair = (30, 22, 18)
    frame[:50] = hair  # a fringe, 10 px into the top of B's face
    points = np.full((68, 2), np.nan)
    points[36:42] = [[44, 100], [50, 96], [56, 96], [62, 100], [56, 104], [50, 104]]  # A's right eye, 18 px wide
    frame[97:104, 40:50] = (40, 30, 30)  # its outer corner and lashes, on B's edge band
    lashes, fringe = np.s_[98:103, 43:49], np.s_[44:48, 90:110]
    without, with_eyes = (composite.blend(face, frame, alpha, points=p) for p in (None, points))
    covered = composite.blend(face, frame, alpha, hair=0)
    print(f"\nlashes: without landmarks {without[lashes].mean():.1f}, with {with_eyes[lashes].mean():.1f}, "
          f"B's face over them {covered[lashes].mean():.1f}")
    assert without[lashes].mean() < covered[lashes].mean() - 20  # the lashes in front: darker
    assert np.abs(with_eyes[lashes].astype(float) - covered[lashes]).mean() < 3  # B's face over them
    assert np.array_equal(with_eyes[fringe], without[fringe])  # the fringe as before
    eyes = composite.features_of(points, alpha.shape)
    assert eyes[100, 35] and eyes[100, 70] and not eyes[100, 75]  # grown 9 px sideways, not more
    assert eyes[92, 53] and not eyes[90, 53]  # and 4-5 px up (96 - 4.5), short of a brow
    assert not composite.features_of(None, alpha.shape).any()


def test_the_puppets_brow_is_not_cut_by_the_drivers_brow_joined_to_its_hair_at_the_edge():
    """A's brow whose outer end lies in B's edge band, joined there to A's hair at the temple (or to a
    glasses' arm), over B's own brow: without A's landmarks it reaches in from beyond B's edge with the
    hair and is kept in front, cutting B's brow short; with them (``features_of(..., BROWS)``: the
    brow's hull grown by a fifth of its width sideways, a tenth up and down) B's brow is drawn there,
    and the hair beyond it is kept. Within A's brow, what is B's skin is still covered by A's hair."""
    face, frame, alpha = lit_scene()  # the disk spans columns 40-160; the band: 14 px inside its edge
    hair = (30, 22, 18)
    frame[78:100, :47] = hair  # hair at the temple, from beyond B's left edge (x 40-42 here) into it
    points = np.full((68, 2), np.nan)
    points[17:22] = [[44, 97], [52, 93], [60, 92], [68, 93], [76, 95]]  # A's right brow, 32 px wide
    frame[92:100, 40:78] = (35, 28, 24)  # the brow, its outer end joined to the hair
    face[95:99, 44:78] = (50, 38, 30)  # B's own brow, thinner, where A's is (in the band from x 44)
    brow, skin, temple = np.s_[96:98, 47:53], np.s_[92:94, 48:53], np.s_[81:85, 44:47]  # skin: B's above it
    brows = composite.features_of(points, alpha.shape, composite.BROWS)
    without, with_brow = (composite.hair_in_front(face, frame, alpha, brows=b) for b in (None, brows))
    print(f"\nB's brow under A's: in front without landmarks {without[brow].min():.2f}, "
          f"with {with_brow[brow].max():.2f}; "
          f"B's skin within A's brow {with_brow[skin].min():.2f}; the temple's hair {with_brow[temple].min():.2f}")
    assert brows[brow].all() and brows[skin].all() and not brows[temple].any()
    assert without[brow].min() > 0.5  # A's brow's end in front of B's, joined to the hair
    assert with_brow[brow].max() < 0.15  # B's brow drawn (a brown brow is a little like skin: 0.1 of A's stays)
    assert with_brow[skin].min() > 0.5 and with_brow[temple].min() > 0.5  # A's hair over B's skin kept


def test_a_background_beside_a_turned_head_is_kept_down_to_the_jaw_without_a_step():
    """A's head turned: his background (not skin) lies under B's right edge from top to bottom. It
    stays in front of B's face along that edge from the temple down to the jaw (B's cheek drawn over
    the wall was a soft band beside the head), changing from one row to the next by at most 0.1
    (a hard cut at half the height jumped by 0.36), and falls off only towards the chin."""
    face, frame, alpha = lit_scene()  # the disk spans rows 40-160, columns 40-160
    frame[:, 150:] = (230, 160, 60)  # an orange wall beside his face
    kept = composite.hair_in_front(face, frame, alpha)[:, 150:].max(axis=1)
    rows = np.arange(75, 126)  # the wall lies under the disk from row 67 to 133, a sliver at its ends
    print(f"\nlargest change from row to row: {np.abs(np.diff(kept[rows])).max():.2f}; "
          f"kept at rows 80 / 100 / 125: {kept[80]:.2f} / {kept[100]:.2f} / {kept[125]:.2f}")
    assert np.abs(np.diff(kept[rows])).max() < 0.1
    assert kept[80] > 0.8 and kept[100] > 0.8 and kept[125] > 0.8


def test_blending_a_box_about_the_face_is_blending_the_whole_frame():
    # a small face off centre in a wide frame: only a box about it is blended, with the same result
    rng = np.random.default_rng(2)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (300, 640, 3), dtype=np.uint8), (0, 0), 2)
    face = np.clip(150 + rng.normal(0, 20, frame.shape), 0, 255).astype(np.uint8)
    alpha = np.zeros(frame.shape[:2], np.float32)
    alpha[60:200, 380:500] = feathered_disk(140, 60)[0][:, 10:130]
    whole = composite._pyramid_blend(face, frame, alpha, composite.levels_for(alpha))
    boxed = composite.multiband(face, frame, alpha)
    assert np.array_equal(boxed, whole)
    assert np.array_equal(boxed[:, :100], frame[:, :100])  # far from the face: A's frame itself


def test_each_levels_weight_is_the_mask_eroded_by_half_its_pixel():
    """An oval face mask 540 x 680 px with a soft edge, on a 900 x 1600 frame (7 levels): each level's
    weight is, to within 0.05 at any pixel and 0.005 on average (measured: 0.031 and 0.0021 at worst), the mask eroded at full size by a disc
    of half the level's pixel and then reduced (the definition; computed faster two levels up)."""
    alpha = np.zeros((900, 1600), np.float32)
    cv2.ellipse(alpha, (800, 450), (270, 340), 0, 0, 360, 1.0, -1)
    alpha = cv2.GaussianBlur(alpha, (0, 0), 2.0)
    levels = composite.levels_for(alpha)
    assert levels == 7
    for k, got in enumerate(composite._level_weights(alpha, levels)):
        r = 2 ** k // 2
        want = cv2.erode(alpha, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) if r else alpha
        for _ in range(k):
            want = cv2.pyrDown(want)
        error = np.abs(got - want)
        assert got.shape == want.shape and error.max() < 0.05 and error.mean() < 0.005, (k, error.max(), error.mean())


def test_steady_light_outvotes_a_frames_odd_fit_and_follows_a_slow_change():
    """Planes of 40 frames: a slow ramp of light (0.01 a frame in every term, 10 % in ten frames) with
    one frame's fit thrown off by 0.5 (hair under B's edge) and one frame without a fit (NaN). Made
    steady at σ 2 frames: the thrown frame is back on the ramp and every frame five or more from the
    ends is within 0.01 of it (measured 0.008 at most: the median of a window of a ramp that holds the
    thrown value moves half a step); the frame without a fit takes its neighbours' (within 0.005);
    σ 0 leaves the planes as they are."""
    t = np.arange(40, dtype=np.float64)
    planes = np.broadcast_to(0.01 * t[:, None, None], (40, 4, 3)).copy()
    truth = planes.copy()
    planes[12] += 0.5
    planes[25] = np.nan
    steady = composite.steady_light(planes, 2.0)
    assert np.abs(steady[5:35] - truth[5:35]).max() < 0.01
    assert np.abs(steady[25] - truth[25]).max() < 0.005
    np.testing.assert_array_equal(composite.steady_light(planes, 0), planes)


def test_the_built_in_composite_and_light_backends_are_the_blend_and_the_steady_light():
    """The kinds' defaults (plugins/builtin/composite.py) call the maths here unchanged, with their params."""
    from persona.plugins.builtin.composite import MultibandComposite, SteadyLight
    from persona.plugins.manager import default_registry

    registry = default_registry()
    assert registry.default("composite") == "multiband" and registry.default("light") == "steady"
    face, frame, alpha, disk = scene()
    plane = composite.light_plane(face, frame, alpha)
    settings = {"lighting": 0.8, "tone": 0.5, "tone_reach": 0.2, "hair": 0.5}
    made = MultibandComposite(settings).composite(face, frame, alpha, plane=plane)
    assert made.dtype == np.uint8 and made.shape == frame.shape
    assert np.array_equal(made, composite.blend(face, frame, alpha, plane=plane, **settings))
    planes = np.random.default_rng(1).normal(0, 0.1, (9, 4, 3)).astype(np.float32)
    planes[4] = np.nan
    assert np.array_equal(SteadyLight({"sigma": 2}).light(planes), composite.steady_light(planes, 2), equal_nan=True)
    # their cache keys are those of the stages before they had backends: "-" and those stages' versions
    assert (MultibandComposite.key_name, MultibandComposite.version) == ("-", "12")
    assert (SteadyLight.key_name, SteadyLight.version) == ("-", "1")
    try:
        SteadyLight().light(planes[0])
    except ValueError:
        pass
    else:
        raise AssertionError("planes of one frame, not (T, 4, 3), must raise ValueError")


def test_a_light_is_read_over_the_face_not_only_its_rim():
    """A's light across the face is fitted on the face's outer fifth (``LIGHT_BAND``), not its rim alone: with
    the left cheek's last 4 px (of a face 120 px across) in a shade the rest of the face does not have (a turned
    cheek's edge, a strand's shadow), a ring of 6 % lies inside that shade, and B's face is lit half as steeply
    again as A's frame is lit across it. The fitted gradient, in log colour across the face's box, against A's
    own 0.36: measured 0.41 on the fifth, 0.54 on the 6 % ring (0.36 on both without the shade)."""
    face, frame, alpha = lit_scene()
    size = alpha.shape[0]
    ys, xs = np.mgrid[0:size, 0:size]
    rim = (alpha > 0) & (np.hypot(ys - size / 2, xs - size / 2) > 56) & (xs < size / 2)
    frame[rim] = (frame[rim] * 0.75).astype(np.uint8)
    x0, x1 = np.flatnonzero(alpha.max(axis=0) > 0.5)[[0, -1]]
    truth = np.log((0.7 + 0.6 * x1 / size) / (0.7 + 0.6 * x0 / size))  # lit_scene's light across the face's box
    fifth = composite.light_plane(face, frame, alpha)[1].mean()
    ring = composite.light_plane(face, frame, alpha, band=0.06)[1].mean()
    print(f"\ngradient across the face: A's {truth:.2f}, fitted on the fifth {fifth:.2f}, on a 6 % ring {ring:.2f}")
    assert abs(fifth - truth) < 0.08 and abs(ring - truth) > 2 * abs(fifth - truth)


def two_lights(tilt=0.15):
    """lit_scene's frame with A's skin in two lights: its tint changes across the frame (log red up and log blue
    down by ``tilt`` from the middle to the right edge, the reverse to the left; a lamp on one side, a window on
    the other), and a dark fringe over the top of B's face."""
    face, frame, alpha = lit_scene()
    across = (np.arange(frame.shape[1]) - frame.shape[1] / 2) / (frame.shape[1] / 2)  # -1 .. 1
    tint = np.exp(tilt * across[None, :, None] * np.array([1.0, 0.0, -1.0]))
    lit = np.clip(frame * tint, 0, 255).astype(np.uint8)
    lit[:50] = (30, 22, 18)  # A's fringe, 10 px into the top of B's face (rows 40-160)
    return face, lit, alpha


def test_a_face_in_two_lights_is_skin_on_both_sides_and_its_fringe_still_hair():
    """A's skin is judged against A's middle carried across the face in A's light (``skin_light``), not against
    one colour: the cheeks of a face whose tint changes by 0.15 from its middle to either side are skin, so
    neither is kept in front of B's face (with one colour for the skin both were, about 0.45); the fringe above
    them is still hair, and the light's fit follows the tint across the face."""
    face, frame, alpha = two_lights()
    kept = composite.hair_in_front(face, frame, alpha)
    cheeks = np.s_[90:110, 42:50], np.s_[90:110, 150:158]  # inside B's edge band, left and right
    fringe = np.s_[44:48, 90:110]
    print(f"\nkept in front: cheeks {kept[cheeks[0]].max():.2f} / {kept[cheeks[1]].max():.2f}, "
          f"fringe {kept[fringe].min():.2f}")
    assert max(kept[c].max() for c in cheeks) < 0.05 and kept[fringe].min() > 0.9
    # the red gain rises and the blue falls across the face's box as A's tint does
    plane = composite.light_plane(face, frame, alpha)
    x0, x1 = np.flatnonzero(alpha.max(axis=0) > 0.5)[[0, -1]]
    truth = 0.15 * 2 * (x1 - x0) / frame.shape[1]  # the tint's change in log colour across the box
    print(f"tint across the face's box, red / blue: {plane[1, 0] - plane[1, 1]:.3f} / "
          f"{plane[1, 2] - plane[1, 1]:.3f}, A's ±{truth:.3f}")
    assert abs((plane[1, 0] - plane[1, 1]) - truth) < 0.05 and abs((plane[1, 2] - plane[1, 1]) + truth) < 0.05
