"""The 3D render backend ``mesh3d`` against the synthetic ground-truth renderer.

The synthetic face's parametrised mesh ``verts`` and painted albedo ``vert_albedo`` are exactly a
puppet mesh and texture on the canonical grid. ``render_photo`` ray-casts the same mesh with
open3d; under a flat ambient light (``Light(1, (0, 0, 0))``) its image is the albedo, so the two
renders must agree pixel for pixel up to the texture lookup (bilinear in (u, v) here, barycentric
over vertex colours there: about 0.2 grey levels on average, a few tens at the pupils' edges).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from persona.plugins.builtin.render3d import RaycastRender, footprint_sample, surface_map, texture_sample
from persona.plugins.face import composite
from persona.plugins.face.synthetic import Expression, Light, look_at_pose, make_face, render_photo
from persona.plugins.kinds import Pose, Puppet
from persona.plugins.manager import default_registry

SIZE = (260, 240)  # frame (h, w)
FLAT = Light(ambient=1.0, direction=(0.0, 0.0, 0.0))  # image = albedo


def puppet_of(face, coverage=None) -> Puppet:
    """The synthetic face as a puppet: mesh = verts on the face, NaN off it; texture = albedo."""
    mesh = np.where(face.vert_mask[..., None], face.verts, np.nan).astype(np.float32)
    if coverage is None:
        coverage = np.ones(face.vert_mask.shape, np.float32)
    return Puppet(appearance=(face.vert_albedo * 255).astype(np.float32), coverage=coverage,
                  fiducials=face.fiducials3d[:, :2], mesh=mesh)


def posed(yaw, pitch=0.0, roll=0.0, face_px=170.0):
    rvec, tvec, camera = look_at_pose(yaw, pitch, roll, face_px=face_px, image_size=SIZE)
    return Pose(rvec, tvec, camera, 0.0)


def truth(face, pose):
    return render_photo(face, rvec=pose.rvec, tvec=pose.tvec, camera=pose.camera, light=FLAT, image_size=SIZE)


def render(puppet, pose, **params):
    """The render with a hard edge, and the texture sampled at a point per pixel, bilinearly, as the ray
    cast interpolates its vertex colours, all of the texture drawn, its rim too (``filter_texture`` off,
    ``sampling`` bilinear, ``rim`` texture: each has its own test below; the ground truth draws the synthetic
    face's cap of hair as face)."""
    frame = np.zeros((*SIZE, 3), np.uint8)
    params = {"feather": 0.0, "filter_texture": False, "sampling": "bilinear", "rim": "texture", **params}
    return RaycastRender(params).render(puppet, None, pose, frame)


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.mark.parametrize("yaw, pitch, roll", [(0, 0, 0), (35, 10, 5), (-30, -12, -8)])
def test_matches_ground_truth_render(yaw, pitch, roll):
    # at 35° yaw the nose hides part of the far cheek: the depth test must keep the nearest surface
    face = make_face()
    pose = posed(yaw, pitch, roll)
    gt = truth(face, pose)
    out = render(puppet_of(face), pose)
    face_px = out.mask > 0.5
    assert iou(face_px, gt.face_mask) > 0.995
    error = np.abs(out.rgb.astype(float) - gt.image.astype(float))[face_px & gt.face_mask]
    assert error.mean() < 1.0  # grey levels (measured: 0.2)
    assert np.percentile(error, 99) <= 4


def test_expression_mesh_renders_where_the_truth_does():
    neutral = make_face()
    open_smile = make_face(expression=Expression(smile=0.8, open=0.8))
    pose = posed(15, 5)
    gt = truth(open_smile, pose)
    # the albedo is painted on the parametrisation: the expression moves only the mesh
    moved = render(puppet_of(open_smile), pose)
    still = render(puppet_of(neutral), pose)
    assert iou(moved.mask > 0.5, gt.face_mask) > 0.995
    both = (moved.mask > 0.5) & gt.face_mask
    moved_error = np.abs(moved.rgb.astype(float) - gt.image.astype(float))[both]
    still_error = np.abs(still.rgb.astype(float) - gt.image.astype(float))[both]
    assert moved_error.mean() < 1.0
    assert still_error.mean() > 5 * moved_error.mean()  # the test sees the expression


@pytest.mark.parametrize("yaw", [20, -45])
def test_surface_map_gives_the_true_texture_coordinates_and_depth(yaw):
    # self-occlusion (nose over cheek) shows here rather than in colour, where it is skin on skin
    face = make_face(expression=Expression(smile=0.5, brow=0.5))
    pose = posed(yaw, -5, 3)
    gt = truth(face, pose)
    box, uv, depth = surface_map(puppet_of(face).mesh, pose, SIZE)
    x0, y0, x1, y1 = box
    hit = np.isfinite(depth)
    both = hit & gt.face_mask[y0:y1, x0:x1]
    assert both.sum() > 0.99 * gt.face_mask.sum()
    assert np.abs(uv - gt.uv[y0:y1, x0:x1])[both].max() < 0.02  # canonical px
    assert np.abs(depth[both] - gt.depth[y0:y1, x0:x1][both]).max() < 0.01
    assert np.all(uv[~hit] == -1)


def test_translation_moves_the_face_with_the_truth():
    face = make_face()
    pose = posed(0)
    shifted = Pose(pose.rvec, pose.tvec + np.array([20.0, -10.0, 0.0]), pose.camera, 0.0)
    before, after = render(puppet_of(face), pose).mask > 0.5, render(puppet_of(face), shifted).mask > 0.5
    assert iou(before, after) < 0.75
    assert iou(after, truth(face, shifted).face_mask) > 0.995


def test_output_shapes_and_types():
    face = make_face()
    frame = np.full((*SIZE, 3), 7, np.uint8)
    out = RaycastRender().render(puppet_of(face), np.zeros((49, 2)), posed(10), frame)
    assert out.rgb.shape == (*SIZE, 3) and out.rgb.dtype == np.uint8
    assert out.mask.shape == SIZE and out.mask.dtype == np.float32
    assert 0 <= out.mask.min() and out.mask.max() <= 1
    assert np.all(out.rgb[out.mask == 0] == 128)  # grey background by default
    assert np.all(out.mask[0] == 0) and np.all(out.mask[:, 0] == 0)


def test_feather_softens_the_edge_inwards():
    face = make_face()
    hard = render(puppet_of(face), posed(10))
    soft = render(puppet_of(face), posed(10), feather=3.0)
    assert set(np.unique(hard.mask)) <= {0.0, 1.0}
    edge = (soft.mask > 0.05) & (soft.mask < 0.95)
    assert edge.sum() > 500
    assert np.all(soft.mask[hard.mask == 0] == 0)  # no face outside the surface
    assert np.all(soft.mask <= hard.mask + 1e-6)


def test_the_soft_edge_keeps_the_face_colour():
    # rgb is the face's own colour across the feathered edge; blending is the caller's (composite,
    # puppet.mp4). A render blended over grey here would carry grey into the composite as a ring.
    face = make_face()
    puppet = puppet_of(face)
    colour = np.array([200.0, 90.0, 60.0], np.float32)
    puppet = Puppet(np.broadcast_to(colour, puppet.appearance.shape).copy(), puppet.coverage,
                    puppet.fiducials, mesh=puppet.mesh)
    out = RaycastRender({"feather": 3.0}).render(puppet, None, posed(0), np.zeros((*SIZE, 3), np.uint8))
    edge = (out.mask > 0) & (out.mask < 0.9)
    assert edge.sum() > 300
    assert np.abs(out.rgb[edge] - colour).max() <= 1
    shown = composite.alone(out.rgb, out.mask)  # over grey, as puppet.mp4
    expected = colour * out.mask[edge][:, None] + 128 * (1 - out.mask[edge][:, None])
    assert np.abs(shown[edge] - expected).max() <= 1
    same = np.broadcast_to(colour.astype(np.uint8), out.rgb.shape)  # a frame of the face's colour
    assert np.abs(composite.paste(out.rgb, same, out.mask).astype(float) - colour).max() <= 1


def test_mask_respects_coverage():
    face = make_face()
    pose = posed(0)
    gt = truth(face, pose)
    coverage = np.ones(face.vert_mask.shape, np.float32)
    coverage[:, :97] = 0.2  # the face's right half (image left) seen by too few photos
    out = render(puppet_of(face, coverage), pose, min_coverage=0.3)
    u = gt.uv[..., 0]
    assert np.all(out.mask[gt.face_mask & (u < 95.5)] == 0)
    assert np.all(out.mask[gt.face_mask & (u > 97.5)] == 1)
    assert np.all(out.rgb[gt.face_mask & (u < 95.5)] == 128)
    everything = render(puppet_of(face, coverage), pose, min_coverage=0.1)
    assert iou(everything.mask > 0.5, gt.face_mask) > 0.995


def test_a_hole_the_face_encloses_is_drawn_though_few_photos_see_it():
    """Texels under the nose that few photos see (coverage 0.1, under ``min_coverage``), enclosed by the face's
    well-seen texels: drawn like the rest (mask 1), not a hole through which the frame shows.
    A gap that reaches the face's edge is still left out."""
    face = make_face()
    pose = posed(0)
    gt = truth(face, pose)
    coverage = np.ones(face.vert_mask.shape, np.float32)
    coverage[140:150, 85:110] = 0.1  # inside the face
    coverage[:, :20] = 0.1  # its edge
    out = render(puppet_of(face, coverage), pose, min_coverage=0.3)
    u, v = gt.uv[..., 0], gt.uv[..., 1]
    inside = gt.face_mask & (u > 87) & (u < 108) & (v > 142) & (v < 148)
    assert inside.sum() > 20 and np.all(out.mask[inside] == 1)
    assert np.all(out.mask[gt.face_mask & (u < 18)] == 0)


def test_bs_hair_at_the_rim_of_the_texture_is_left_out_and_bs_brows_are_drawn():
    """Hair that hung over B's temple and cheek in B's photos is in B's texture as a dark band reaching its edge.
    With ``rim: skin`` (the default) it is not drawn, nor is the cap of hair at the top of the synthetic face's
    texture: the frame shows there, as beside a face narrower than B's. The skin beside the strand is drawn, and so
    is B's brow, though a strand joins its outer end to the edge. With ``rim: texture`` (the paper's) all of it is."""
    face, pose = make_face(), posed(0)
    gt = truth(face, pose)
    puppet = puppet_of(face, face.vert_mask.astype(np.float32))  # no photo sees beyond the face
    albedo, hair = puppet.appearance.copy(), np.float32([45, 32, 25])
    rows, cols = np.nonzero(face.vert_mask)
    edge = {r: cols[rows == r].min() for r in range(60, 180)}  # the face's left edge, by texel row
    strand = np.zeros(face.vert_mask.shape, bool)
    for r in range(115, 155):
        strand[r, edge[r]:edge[r] + 10] = True  # down the cheek, 10 texels deep: below the eye, above the chin
    bridge = np.zeros_like(strand)
    for r in range(80, 88):
        bridge[r, edge[r]:34] = True  # from the edge to the brow's outer end (fiducial 0 at x 34, y 84)
    albedo[strand | bridge] = hair
    puppet = Puppet(**{**puppet.__dict__, "appearance": albedo})
    u, v = (np.clip(np.round(np.nan_to_num(gt.uv[..., k])), 0, n - 1).astype(int) for k, n in ((0, 194), (1, 244)))
    seen = gt.face_mask & np.isfinite(gt.uv).all(axis=-1)
    ring = np.ones((5, 5), np.uint8)  # two texels in: the mask's samples between texels are read bilinearly
    deep = lambda texels: seen & (cv2.erode(texels.astype(np.uint8), ring)[v, u] > 0)  # noqa: E731
    skin = np.zeros_like(strand)
    for r in range(115, 155):
        skin[r, edge[r] + 30:edge[r] + 40] = True
    brow = np.zeros_like(strand)
    for x, y in np.round(face.fiducials3d[:5, :2]).astype(int):  # the left brow's five points
        brow[y - 3:y + 4, x - 3:x + 4] = True
    cap = face.vert_mask & (np.arange(244)[:, None] < 20)  # the synthetic texture's hair, at its top
    assert (albedo[cap].mean(axis=0) < 80).all()  # dark: hair, not skin

    out = render(puppet, pose, rim="skin")
    for texels in (strand, cap):
        assert deep(texels).sum() > 50 and np.all(out.mask[deep(texels)] == 0)
    for texels in (skin, brow):
        assert deep(texels).sum() > 20 and np.all(out.mask[deep(texels)] == 1)
    everything = render(puppet, pose)
    assert np.all(everything.mask[deep(strand) | deep(cap)] == 1)
    # judged on B's neutral texture when the puppet has one, whatever this frame's texture holds there
    clean = Puppet(**{**puppet.__dict__, "appearance": puppet_of(face).appearance, "neutral": albedo})
    assert np.all(render(clean, pose, rim="skin").mask[deep(strand)] == 0)


def test_missing_mesh_is_a_clear_error():
    face = make_face()
    flat = Puppet(puppet_of(face).appearance, np.ones(face.vert_mask.shape, np.float32), np.zeros((49, 2)))
    with pytest.raises(ValueError, match="needs the puppet's 3D mesh"):
        RaycastRender().render(flat, None, posed(0), np.zeros((*SIZE, 3), np.uint8))


def test_face_off_frame_gives_background_only():
    face = make_face()
    pose = posed(0)
    away = Pose(pose.rvec, pose.tvec + np.array([10.0, 0.0, 0.0]) * pose.tvec[2], pose.camera, 0.0)
    out = RaycastRender().render(puppet_of(face), None, away, np.zeros((*SIZE, 3), np.uint8))
    assert not out.mask.any() and np.all(out.rgb == 128)


def test_params_are_validated():
    with pytest.raises(ValueError):
        RaycastRender({"min_coverage": 1.5})
    with pytest.raises(ValueError):
        RaycastRender({"feather": -1})
    with pytest.raises(ValueError):
        RaycastRender({"background": "grey"})  # gone: the caller blends (test above)


def test_registered_as_a_render_backend():
    registry = default_registry()
    assert registry.get("render", "mesh3d") is RaycastRender
    assert registry.default("render") == "mesh3d"


def _stripes(h=244, w=194):
    """A texture of one-texel vertical stripes, 200 and 50: its mean is 125."""
    row = np.where(np.arange(w) % 2 == 0, 200.0, 50.0)
    return np.repeat(np.repeat(row[None, :, None], h, axis=0), 3, axis=2).astype(np.float32)


def test_a_face_smaller_than_its_texture_is_sampled_over_each_pixels_footprint():
    """One-texel stripes seen two texels to a pixel: bilinear sampling at the pixel centres lands on
    one stripe every time (200 throughout: aliasing); the footprint's filter gives their mean, 125."""
    texture = _stripes()
    ys, xs = np.mgrid[0:100, 0:80].astype(np.float32)
    u, v = 2 * xs, 2 * ys
    inside = np.s_[5:-5, 5:-5]
    plain = cv2.remap(texture, u, v, cv2.INTER_LINEAR)
    assert np.abs(plain[inside] - 125).min() > 70  # aliased: one stripe's value
    sampled = footprint_sample(texture, u, v)
    assert np.abs(sampled[inside] - 125).max() < 2


def test_a_face_as_large_as_its_texture_or_larger_is_sampled_as_before():
    """A pixel that spans a texel or less (the drives whose faces are larger than the canonical
    grid) is the plain bilinear sample, to the bit; off the surface (NaN) it is 0."""
    texture = _stripes()
    ys, xs = np.mgrid[0:120, 0:100].astype(np.float32)
    for scale in (1.0, 0.5):
        u, v = scale * xs + 3.3, scale * ys + 1.7
        plain = cv2.remap(texture, u, v, cv2.INTER_LINEAR)
        u[:10] = np.nan
        plain[:10] = 0
        np.testing.assert_array_equal(footprint_sample(texture, u, v), plain)


def test_the_footprint_filter_keeps_what_a_pixel_can_show():
    """A smooth ramp seen 1.5 texels to a pixel comes out as bilinear sampling gives it (within a grey
    level): the filter takes out only what is finer than a pixel."""
    ys, xs = np.mgrid[0:244, 0:194].astype(np.float32)
    texture = np.repeat((40 + 0.6 * xs + 0.3 * ys)[..., None], 3, axis=2).astype(np.float32)
    ys, xs = np.mgrid[0:120, 0:100].astype(np.float32)
    u, v = 1.5 * xs, 1.5 * ys
    inside = np.s_[5:-5, 5:-5]
    assert np.abs(footprint_sample(texture, u, v)[inside] - cv2.remap(texture, u, v, cv2.INTER_LINEAR)[inside]).max() < 1.0


def _waves(period: float, h=244, w=194):
    """A texture of vertical waves, 128 + 100 sin(2π x / period) at each texel's centre, and the wave itself."""
    wave = lambda x: 128 + 100 * np.sin(2 * np.pi * x / period)  # noqa: E731
    row = wave(np.arange(w, dtype=np.float64))
    return np.repeat(np.repeat(row[None, :, None], h, axis=0), 3, axis=2).astype(np.float32), wave


def test_a_face_larger_than_its_texture_keeps_what_lies_between_its_texels():
    """Waves 5 texels long seen at two pixels a texel (a face at HD on the canonical grid): the bicubic
    sample follows the wave between texel centres within 3 grey levels (RMS, of its 100 of amplitude), and
    keeps at least 0.97 of its amplitude; the bilinear sample cuts across each crest and trough, losing over
    a tenth of it."""
    texture, wave = _waves(5.0)
    ys, xs = np.mgrid[0:100, 0:150].astype(np.float32)
    u, v = 0.5 * xs + 7.25, 0.5 * ys + 3.6
    truth = wave(u.astype(np.float64))
    for sampling, most_error, least_amplitude in (("bicubic", 3.0, 97), ("bilinear", None, None)):
        grey = texture_sample(texture, u, v, sampling=sampling)[..., 0]
        error = float(np.sqrt(np.mean((grey - truth) ** 2)))
        amplitude = np.std(grey) * np.sqrt(2)
        if most_error is not None:
            assert error < most_error and amplitude > least_amplitude, (sampling, error, amplitude)
        else:
            assert error > 6 and amplitude < 92, (sampling, error, amplitude)


def test_the_bicubic_sample_is_bilinear_where_it_would_reach_a_hole():
    """Texels with no colour (stored as 0) darken the bicubic kernel's reach one texel further than the
    bilinear's: a pixel within two texels of a hole is the bilinear sample, to the bit, and no pixel whose
    bilinear sample sees no hole comes out darker than the texture's darkest colour; further in it is the
    bicubic one."""
    texture, _ = _waves(5.0)
    holes = np.zeros(texture.shape[:2], bool)
    holes[:, :40] = True
    texture[holes] = 0
    ys, xs = np.mgrid[0:80, 0:120].astype(np.float32)
    u, v = 0.5 * xs + 30.3, 0.5 * ys + 10.2
    linear = cv2.remap(texture, u, v, cv2.INTER_LINEAR)
    cubic = cv2.remap(texture, u, v, cv2.INTER_CUBIC)
    sampled = texture_sample(texture, u, v, holes, "bicubic")
    near = u < 41  # the bicubic kernel of a pixel at u < 41 reads texel 39 (floor(u) - 1)
    np.testing.assert_array_equal(sampled[near], linear[near])
    np.testing.assert_array_equal(sampled[~near], cubic[~near])
    assert sampled[u >= 40].min() >= 28 - 1  # the wave's trough, 128 - 100, within a grey level


def test_the_render_filters_a_texture_it_draws_smaller():
    """The synthetic face at 100 px between its temples, smaller than its texture, with one-texel
    stripes for a texture: with ``filter_texture`` the face comes out about the stripes' mean, 125
    (its darkest and lightest tenths within 20 levels of it); with point samples it is striped."""
    face = make_face()
    puppet = puppet_of(face)
    puppet = Puppet(_stripes(*puppet.appearance.shape[:2]), puppet.coverage, puppet.fiducials, mesh=puppet.mesh)
    pose, frame = posed(0, face_px=100.0), np.zeros((*SIZE, 3), np.uint8)
    filtered = RaycastRender({"feather": 0.0, "filter_texture": True}).render(puppet, None, pose, frame)
    points = RaycastRender({"feather": 0.0, "filter_texture": False}).render(puppet, None, pose, frame)
    inner = cv2.erode((filtered.mask > 0.5).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    grey = lambda out: out.rgb[inner].mean(axis=-1)  # noqa: E731
    assert np.abs(np.percentile(grey(filtered), [10, 90]) - 125).max() < 20
    assert np.percentile(grey(points), 90) - np.percentile(grey(points), 10) > 60


def test_the_face_is_drawn_only_above_bs_jaw_line_with_a_jaw_margin():
    """With ``jaw_margin`` (2 px, the default), B's face ends at B's jaw line moved that far outwards
    (mesh.above_jaw): no pixel whose texel lies well outside it is drawn, every one well inside is; without it
    (None, the paper's), the whole face is."""
    from persona.plugins.face.mesh import above_jaw

    face, pose = make_face(), posed(10)
    gt = truth(face, pose)
    jaw = face.landmarks3d[:17, :2] - [0.0, 12.0]  # a jaw line 12 px over the mesh's chin: a face with a neck below
    puppet = Puppet(**{**puppet_of(face).__dict__, "jaw": jaw})
    out = render(puppet, pose, jaw_margin=2.0)
    inside = gt.face_mask & np.isfinite(gt.uv).all(axis=-1)
    u, v = (np.clip(np.round(np.nan_to_num(gt.uv[..., k])), 0, n - 1).astype(int) for k, n in ((0, 194), (1, 244)))
    kept, ring = (above_jaw(jaw, (244, 194), 2.0) > 0.5).astype(np.uint8), np.ones((5, 5), np.uint8)
    well_outside, well_inside = cv2.dilate(kept, ring)[v, u] == 0, cv2.erode(kept, ring)[v, u] > 0
    assert (inside & well_outside).sum() > 1000  # the mesh reaches below that line: the test can fail
    assert np.all(out.mask[inside & well_outside] == 0)
    assert np.all(out.mask[inside & well_inside] == 1)
    assert iou(render(puppet, pose, jaw_margin=None).mask > 0.5, gt.face_mask) > 0.995
