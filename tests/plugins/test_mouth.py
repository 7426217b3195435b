"""The inside of the mouth (persona.plugins.face.mouth): taken from open-mouth photos, drawn between
the lips where the puppet's mesh parts them."""

from __future__ import annotations

import numpy as np

from persona.plugins.builtin.render3d import RaycastRender
from persona.plugins.face import mouth
from persona.plugins.face.synthetic import Expression, look_at_pose, make_face
from persona.plugins.face.template import IDX49
from persona.plugins.kinds import Pose, Puppet

BLUE = np.array([0.0, 0.0, 255.0], np.float32)


def open_photo(gap: float, width: float = 60.0, size: int = 160):
    """A white photo with a black mouth between two lips ``gap`` px apart (both curves straight, the
    inner corners at the gap's middle height), and its 68 landmarks (eyes 50 px apart)."""
    rgb = np.full((size, size, 3), 255, np.uint8)
    lm = np.zeros((68, 2))
    lm[36:42] = [55, 60]
    lm[42:48] = [105, 60]
    cx, cy = 80.0, 110.0
    xs = cx + width * (np.arange(5) / 4 - 0.5)
    lm[[60, 61, 62, 63, 64]] = np.c_[xs, np.r_[cy, [cy - gap / 2] * 3, cy]]
    lm[[60, 67, 66, 65, 64]] = np.c_[xs, np.r_[cy, [cy + gap / 2] * 3, cy]]
    top, bottom = int(round(cy - gap / 2)), int(round(cy + gap / 2))
    rgb[top:bottom + 1, int(xs[1]):int(xs[3]) + 1] = 0
    return rgb, lm


def test_gap_and_the_widest_photos():
    photos = [open_photo(g) for g in (4.0, 20.0, 0.0, 12.0)]
    landmarks = np.stack([p[1] for p in photos])
    landmarks[3, 62] = np.nan  # a photo with a missing point is never chosen
    np.testing.assert_allclose(mouth.lip_gap(landmarks)[:3], [4 / 50, 20 / 50, 0.0])  # over the eyes' 50 px
    assert np.isnan(mouth.lip_gap(landmarks)[3])
    assert list(mouth.widest(landmarks, count=5, min_gap=0.05)) == [1, 0]
    assert list(mouth.widest(landmarks, count=1, min_gap=0.05)) == [1]
    assert len(mouth.widest(landmarks, count=5, min_gap=1.0)) == 0


def test_interior_is_the_photos_gap():
    """The gap of a photo is black between its inner lips, white outside: the interior image is
    black in its middle columns from top to bottom, whatever the gap's size."""
    image = mouth.interior(mouth.sample(*open_photo(gap)) for gap in (24.0, 12.0, 30.0))
    rows, cols = mouth.SIZE
    assert image.shape == (rows, cols, 3)
    middle = image[2:-2, int(cols * 0.3):int(cols * 0.7)]
    assert middle.max() < 40, middle.max()
    assert mouth.interior([]) is None


def test_the_darkest_gaps_are_those_that_show_the_cavity():
    # a laugh's gap is mostly teeth and tongue (bright), an open mouth's mostly cavity (dark); the lips'
    # own colour at the gap's edges (its top and bottom rows) does not count
    samples = []
    for middle in (200, 30, 120, 10):
        rgb, lm = open_photo(24.0)
        rgb[100:121, 60:101] = middle  # the gap's middle rows: teeth, cavity, tongue
        samples.append(mouth.sample(rgb, lm))
    samples = np.stack(samples)
    samples[1, :3] = 255  # bright lips at the top of the cavity's gap: no matter
    assert list(mouth.darkest(samples, 2)) == [3, 1]
    assert list(mouth.darkest(samples, 9)) == [3, 1, 2, 0]


def test_the_driver_shows_teeth_or_the_cavity_against_its_own_nose():
    def frame(middle: int, gap: float = 24.0):
        rgb, lm = open_photo(gap)
        rgb[:] = 150  # skin, the nose's grey too
        top, bottom = int(round(110 - gap / 2)), int(round(110 + gap / 2))
        rgb[top:bottom + 1, 65:96] = middle
        lm[[29, 30, 31, 32, 33, 34, 35]] = [[80, 70], [80, 78], [72, 86], [76, 87], [80, 88], [84, 87], [88, 86]]
        return rgb, lm
    cavity, teeth, half = (mouth.teeth_share(*frame(m)) for m in (15, 150, 0.45 * 150))
    print(f"\nteeth share: cavity {cavity:.2f}, teeth {teeth:.2f}, half way {half:.2f}")
    assert cavity == 0 and teeth == 1 and abs(half - 0.5) < 0.02  # grey over the nose's: 0.1, 1, 0.45 (0.2 -> 0, 0.7 -> 1)
    assert mouth.teeth_share(*frame(150, gap=1.0)) == 0  # closed lips: the dark line where they meet
    rgb, lm = frame(150)
    lm[62] = np.nan
    assert mouth.teeth_share(rgb, lm) == 0
    image, gap = mouth.for_frame(np.full((2, 2, 3), 200.0), np.full((2, 2, 3), 20.0), (30.0, 10.0), 0.25)
    np.testing.assert_allclose(image, 65.0)
    assert gap == 15.0


def test_draw_fills_the_gap_only_where_the_face_is():
    out = np.full((100, 120, 3), 200, np.uint8)
    face = np.ones((100, 120), np.float32)
    face[:, 90:] = 0  # no face there: nothing is drawn
    xs = np.linspace(20, 100, 5)
    curves = np.stack([np.c_[xs, [50, 40, 40, 40, 50]], np.c_[xs, [50, 60, 60, 60, 50]]])
    mouth.draw(out, face, np.broadcast_to(BLUE, (32, 64, 3)).copy(), curves)
    blue = (out[..., 2] > 200) & (out[..., 0] < 50)
    assert blue[44:57, 40:80].all()  # inside the gap
    assert not blue[:35].any() and not blue[65:].any()  # above and below it
    assert not blue[:, 90:].any()
    closed = np.full((100, 120, 3), 200, np.uint8)
    mouth.draw(closed, face, np.broadcast_to(BLUE, (32, 64, 3)).copy(),
               np.stack([curves[0], curves[0]]))  # lips together: no area, nothing drawn
    assert (closed == 200).all()


def _blue_pixels(expression: Expression, draw: bool, insets=None, corners: str = "driver") -> int:
    face = make_face(expression=expression)
    neutral = make_face()
    lips = mouth.lip_curves(neutral.landmarks3d[:, :2])
    mesh = np.where(face.vert_mask[..., None], face.verts, np.nan).astype(np.float32)
    puppet = Puppet(appearance=(face.vert_albedo * 255).astype(np.float32),
                    coverage=np.ones(face.vert_mask.shape, np.float32),
                    fiducials=neutral.landmarks3d[list(IDX49), :2], mesh=mesh,
                    mouth=np.broadcast_to(BLUE, (32, 64, 3)).copy(), lips=lips, lip_insets=insets)
    rvec, tvec, camera = look_at_pose(0.0, 0.0, 0.0, face_px=170.0, image_size=(260, 240))
    out = RaycastRender({"mouth": draw, "mouth_corners": corners}).render(puppet, None, Pose(rvec, tvec, camera, 0.0),
                                                np.zeros((260, 240, 3), np.uint8))
    rgb = out.rgb.astype(int)
    return int(np.count_nonzero((rgb[..., 2] > 180) & (rgb[..., 0] < 60) & (rgb[..., 1] < 60)))


def _render_open(interior: np.ndarray, gap: float, own: bool) -> np.ndarray:
    """The synthetic face with its jaw dropped, rendered with ``interior`` as its mouth (``own``: the
    driver's, its ``gap`` in frame px; else B's, in canonical px)."""
    face, neutral = make_face(expression=Expression(open=1.0)), make_face()
    puppet = Puppet(appearance=np.full(face.vert_albedo.shape[:2] + (3,), 200, np.float32),
                    coverage=np.ones(face.vert_mask.shape, np.float32),
                    fiducials=neutral.landmarks3d[list(IDX49), :2],
                    mesh=np.where(face.vert_mask[..., None], face.verts, np.nan).astype(np.float32),
                    mouth=interior, lips=mouth.lip_curves(neutral.landmarks3d[:, :2]), mouth_gap=gap, mouth_own=own)
    rvec, tvec, camera = look_at_pose(0.0, 0.0, 0.0, face_px=100.0, image_size=(260, 240))  # half size
    return RaycastRender().render(puppet, None, Pose(rvec, tvec, camera, 0.0), np.zeros((260, 240, 3), np.uint8)).rgb


def test_the_drivers_own_interior_is_fitted_to_its_gap_in_the_frames_pixels():
    """The driver's own interior (white, one dark row in its middle: the dark below the upper
    teeth) drawn into B's opening, given the driver's gap in the frame's px, on a face drawn at about
    half its canonical size. At the opening's own height (measured: 11 px at its middle column)
    nothing is added: the dark stays one row's share of the opening (under 10 %). Given half that
    gap, the jaw dropped twice as far as the driver's, so the dark is parted open to fill about half
    of it (over 40 %). (Taken to canonical px and back
    at the head's distance rather than the lips', the gap came out at 0.54-0.58 of the driver's on a
    real drive, and the dark was parted open where the lips were no further apart than A's.)"""
    image = np.full((32, 64, 3), 255, np.float32)
    image[16] = 0
    rgb = _render_open(np.broadcast_to(BLUE, (32, 64, 3)).copy(), np.inf, own=False).astype(int)
    blue = (rgb[..., 2] > 180) & (rgb[..., 0] < 60)
    column = int(np.median(np.nonzero(blue)[1]))
    height = int(np.count_nonzero(blue[:, column]))

    def dark_share(gap):
        grey = _render_open(image, gap, own=True)[..., 0].astype(int)[blue[:, column], column]
        return np.mean(grey < 100)

    print(f"\nopening {height} px: dark {dark_share(float(height)):.2f} at its own gap, "
          f"{dark_share(height / 2):.2f} at half")
    assert dark_share(float(height)) < 0.1
    assert dark_share(height / 2) > 0.4


def test_the_renderer_shows_the_interior_when_the_lips_part():
    """A synthetic face whose jaw drops: the renderer draws the interior between the lips as the
    mesh moved them (measured 713 px wide open, 227 at rest: the synthetic face's lips rest a little
    apart), only the antialiased rim with the lips closed (11 px), none with ``mouth: false``."""
    wide, rest = _blue_pixels(Expression(open=1.0), draw=True), _blue_pixels(Expression(), draw=True)
    assert wide > 2 * rest > 200
    assert _blue_pixels(Expression(open=-1.0), draw=True) < 30
    assert _blue_pixels(Expression(open=1.0), draw=False) == 0


def test_the_opening_narrows_when_the_drivers_inner_corners_come_in():
    """The same open mouth with its inner corners placed a quarter of the mouth's width in from the
    outer ones (a round "O") covers fewer pixels than where the mesh leaves them (measured 496 against
    713; the synthetic face's own are 0.08 in); ``mouth_corners: mesh`` ignores the insets."""
    mesh = _blue_pixels(Expression(open=1.0), draw=True)
    assert _blue_pixels(Expression(open=1.0), draw=True, insets=np.array([0.25, 0.25]), corners="mesh") == mesh
    assert _blue_pixels(Expression(open=1.0), draw=True, insets=np.array([0.25, 0.25])) < 0.8 * mesh


def test_a_gap_a_pixel_tall_shows_the_interiors_mean_colour_along_it_not_a_speckle_of_its_rows():
    """An interior of alternating white (teeth) and black (cavity) rows, drawn into a gap 1.2 px tall
    and 60 px long whose height wanders by half a pixel, on light grey (200): along the gap's middle
    row every pixel has the same colour to within 8 levels (sampling the rows gave 46-250 from column
    to column), from the interior's mean (127.5, within rounding) towards the grey, as the gap covers
    most of a pixel or all of it."""
    stripes = np.zeros((32, 64, 3), np.float32)
    stripes[::2] = 255
    out = np.full((60, 100, 3), 200, np.uint8)
    xs = np.linspace(20, 80, 5)
    upper = np.array([30, 29.2, 29.7, 29.3, 30])  # a lip line that wanders a little, as a real one does
    curves = np.stack([np.c_[xs, upper], np.c_[xs, upper + [0, 1.2, 1.2, 1.2, 0]]])
    mouth.draw(out, np.ones((60, 100), np.float32), stripes, curves)
    line = out[30, 35:66].astype(float).mean(axis=1)  # between the second and fourth nodes
    print(f"\nthe gap's middle row: {line.min():.0f}-{line.max():.0f}")
    assert np.ptp(line) <= 8 and np.all((line >= 127) & (line < 170))


def test_a_round_mouth_is_drawn_round():
    """Inner lips on a circle of radius 20 px (iBUG 60-64 and 64-60 every 45°, as an "O" puts them):
    the drawn opening covers the circle's area to within 1 % (the polygon of the eight points would
    cover 10 % less: an octagon), and its outline stays within 2 % of the circle."""
    r, centre = 20.0, np.array([50.0, 50.0])
    angles = np.deg2rad([180, 135, 90, 45, 0])
    ring = np.c_[np.cos(angles), np.sin(angles)] * r
    curves = np.stack([centre + ring * [1, -1], centre + ring])
    out = np.zeros((100, 100, 3), np.uint8)
    mouth.draw(out, np.ones((100, 100), np.float32), np.full((32, 64, 3), 255, np.float32), curves)
    area = out[..., 0].sum() / 255
    assert abs(area / (np.pi * r ** 2) - 1) < 0.01, area
    radius = np.linalg.norm(mouth.rounded(curves) - centre, axis=2)
    assert radius.min() > 0.98 * r and radius.max() < 1.02 * r



def test_the_cavity_is_the_interiors_darkest_colour():
    image = np.full((32, 64, 3), 255, np.float32)
    image[12:16, :40] = [40, 10, 10]  # 160 of 2048 pixels: more than the darkest 5 %
    np.testing.assert_allclose(mouth.cavity(image), [40, 10, 10])


def test_depth_is_zero_within_half_the_photos_gap_of_the_lips():
    """An opening 40 px tall for photos whose lips were 16 px apart: no depth within 8 px of its edge,
    all of it from 12 px in, rising between; an opening 16 px tall has none."""
    opening = np.zeros((60, 200), np.uint8)
    opening[10:50, 20:180] = 1
    depth = mouth.depth(opening, 16.0)
    column = depth[:, 100]
    assert (column[10:18] == 0).all() and (column[42:50] == 0).all()  # within 8 px of the lips
    assert (column[22:38] == 1).all()  # 12 px in and more
    assert np.all(np.diff(column[17:23]) >= 0) and 0 < column[20] < 1
    assert not depth[:10].any() and not depth[50:].any()
    short = np.zeros((60, 200), np.uint8)
    short[20:36, 20:180] = 1
    assert not mouth.depth(short, 16.0).any()
    assert not mouth.depth(opening, 0.0).any()  # photos whose lips did not part: nothing to go by


def test_a_mouth_opened_further_than_its_photos_shows_the_cavity_between_its_teeth():
    """An interior of white teeth only (B's photos show a grin), of photos whose lips were 16 px apart,
    drawn on grey into a gap of 16 px and of 40 px: at 16 px it is all teeth, as the photos show; at
    40 px the teeth stay along the lips (the 8 px next to each) and the middle is the cavity's colour."""
    teeth = np.full((32, 64, 3), 255, np.float32)
    teeth[:, :4] = [60, 20, 20]  # a dark rim at the corner (6 % of it): the cavity's colour

    def column(height: float) -> np.ndarray:
        out = np.full((100, 120, 3), 128, np.uint8)
        xs = np.linspace(10, 110, 5)
        curves = np.stack([np.c_[xs, [50, 30, 30, 30, 50]],
                           np.c_[xs, [50, 30 + height, 30 + height, 30 + height, 50]]])
        mouth.draw(out, np.ones((100, 120), np.float32), teeth, curves, gap=16.0)
        return out[:, 60].astype(float)
    grin, jaw = column(16.0), column(40.0)
    assert (grin[31:45] > 240).all()  # (the rounded outline bulges a pixel past the nodes: 247 in its middle)
    assert (jaw[31:37] > 250).all() and (jaw[63:69] > 250).all()  # the teeth along each lip
    np.testing.assert_allclose(jaw[45:55], np.broadcast_to([60, 20, 20], (10, 3)), atol=1)


def test_the_drivers_own_interior_is_taken_inside_its_lips():
    """``mouth_choice: frame``: the driver's gap, sampled a little inside its inner-lip points, which sit
    on the lips' edge: a red lip line 2 px thick along each of them lines the plain sample's first and
    last rows, not the driver's interior, whose middle is the gap's (black): 0.15 of the gap left out
    along each lip (under the cap of 0.03 inter-ocular distances when the eyes are 200 px apart), the
    whole gap (20 px) given as the height it is drawn from."""
    rgb, lm = open_photo(20.0)
    lm[42:48, 0] += 150  # the eyes 200 px apart: the cap (6 px) is above 15 % of the gap (3 px)
    for y in (100, 120):  # the upper and lower inner-lip curves of a 20 px gap about y = 110
        rgb[y - 1:y + 2, 40:121] = (200, 30, 30)
    red = lambda rows: (rows[..., 0] > 120) & (rows[..., 1] < 80)
    plain = mouth.sample(rgb, lm)
    assert red(plain[0, 16:48]).all() and red(plain[-1, 16:48]).all()
    interior, gap = mouth.from_frame(rgb, lm)
    assert interior.shape[0] == mouth.SIZE[0]  # 14 px spanned: SIZE's 32 rows at least
    middle = interior[:, interior.shape[1] // 3:2 * interior.shape[1] // 3]  # the gap's black spans its middle
    assert not red(middle).any()
    assert middle[2:-2].max() < 40
    assert gap == 20.0
    assert mouth.from_frame(*open_photo(1.0)) is None  # lips under 2 px apart: no interior is drawn
    # at HD (the eyes 150 px apart) lips 4 px apart are closed lips as dlib reads them (0.027 of the
    # eyes' distance, under 0.04); 8 px apart (0.053) they part
    for gap, parts in ((4.0, False), (8.0, True)):
        rgb, hd = open_photo(gap)
        hd[42:48, 0] += 100  # the eyes 150 px apart
        assert (mouth.from_frame(rgb, hd) is not None) == parts
        assert mouth.from_frame(rgb, hd, min_gap=0.0) is not None  # 2 px alone, at any resolution
    lm[66] = np.nan
    assert mouth.from_frame(rgb, lm) is None


def test_a_wide_open_mouth_keeps_the_teeth_that_hang_from_its_lips():
    """A mouth open 60 px with the eyes 100 px apart (0.6 of their distance), a row of teeth 6 px tall
    (white) under the upper lip's points and over the lower's, dark between: the interior is taken 3 px
    (0.03 inter-ocular distances) inside each lip, not 15 % of the gap (9 px, past the teeth), so both
    rows of teeth are in it; its rows and columns are the frame's pixels (54 spanned, 129 along the lips),
    not SIZE's 32 x 64. Without the cap (``max_inset`` None) the teeth are cut off."""
    rgb, lm = open_photo(60.0, width=100.0)
    lm[42:48, 0] += 50  # the eyes 100 px apart
    rgb[80:87, 55:106] = 255  # upper teeth, from the upper lip's points at y = 80 down
    rgb[134:141, 55:106] = 255  # lower teeth, up from the lower lip's at y = 140
    white = lambda rows: rows[..., 1].mean() > 200
    interior, gap = mouth.from_frame(rgb, lm)
    assert gap == 60.0 and interior.shape == (54, 129, 3)  # 54 px spanned; the lip curves 128.1 px long
    middle = interior[:, 50:80]  # the middle of the mouth, between the middle lip points
    assert white(middle[:2]) and white(middle[-2:]) and middle[20:34].max() < 40
    interior, gap = mouth.from_frame(rgb, lm, max_inset=None)
    assert gap == 60.0 and interior.shape[0] == 42
    assert interior[:, 40:60].max() < 40  # 9 px inside each lip: no tooth left


def test_lips_closer_than_the_interiors_own_keep_its_teeth_at_their_size():
    """An interior whose top and bottom 10 of 32 rows are teeth (white) and middle cavity (black), from
    lips 20 px apart, drawn between lips 10 px apart: squeezed, the gap's middle row is the cavity;
    with ``keep_rows`` the rows nearest each lip keep their size and the middle is left out, so the
    gap shows the teeth from lip to lip. Lips as far apart as the interior's own show all of it."""
    image = np.zeros((32, 64, 3), np.float32)
    image[:10] = image[-10:] = 255
    xs = np.linspace(20, 80, 5)
    curves = np.stack([np.c_[xs, np.full(5, 25.0)], np.c_[xs, np.full(5, 35.0)]])  # 10 px apart

    def middle_row(keep_rows, gap):
        out = np.full((60, 100, 3), 128, np.uint8)
        mouth.draw(out, np.ones((60, 100), np.float32), image, curves, gap=gap, keep_rows=keep_rows)
        return out[30, 35:66].astype(float).mean()

    assert middle_row(False, 20.0) < 40
    assert middle_row(True, 20.0) > 215
    assert middle_row(True, 10.0) < 40  # the interior's own gap: nothing left out


def test_a_smile_drawn_into_lips_as_far_apart_keeps_its_teeth_meeting():
    """A driver's smile, lips 20 px apart (eyes 100 px apart: the inset is 15 % of the gap, 3 px): upper
    teeth from the upper lip's points down to 1 px above the middle, lower teeth from 1 px below it, a
    dark line 2 px tall between. Drawn into B's lips as far apart, with the rows kept at their size, the
    teeth meet as they did: the dark between them is the driver's 2 px, not the 6 px the inset leaves out
    put in at the darkest row (a dark bar across the teeth)."""
    rgb, lm = open_photo(20.0)
    lm[42:48, 0] += 50  # the eyes 100 px apart
    rgb[100:121, 40:121] = 255
    rgb[109:111, 40:121] = 0  # the dark line where the teeth meet, about y = 110
    interior, gap = mouth.from_frame(rgb, lm)
    xs = np.linspace(20, 80, 5)
    curves = np.stack([np.c_[xs, np.full(5, 20.0)], np.c_[xs, np.full(5, 40.0)]])  # 20 px apart, as A's
    out = np.full((60, 100, 3), 128, np.uint8)
    mouth.draw(out, np.ones((60, 100), np.float32), interior, curves, gap=gap, keep_rows=True)
    column = out[:, 45:56].astype(float).mean(axis=(1, 2))
    dark = np.flatnonzero(column[20:40] < 128)
    assert 1 <= len(dark) <= 3, column[20:40].round()
    assert column[22:27].min() > 215 and column[33:38].min() > 215  # teeth from each lip to the line


def test_lips_further_apart_than_the_drivers_keep_its_teeth_on_their_lip():
    """The driver's own interior from lips 10 px apart: upper teeth (white) in its top 26 of 32 rows,
    the dark below them. Drawn with ``keep_rows`` between lips 20 px apart (rows 20 to 40), the teeth
    keep their size on the upper lip (white 4 px below it: 26 / 32 of 10 px) and the dark fills the
    rest down to the lower lip (from 10 px below the upper lip to 1 px above the lower), where
    stretched and darkened in the middle (the photos' way, without ``keep_rows``) the teeth would
    reach down to the lower lip too, split by the dark."""
    image = np.zeros((32, 64, 3), np.float32)
    image[:26] = 255
    xs = np.linspace(20, 80, 5)
    curves = np.stack([np.c_[xs, np.full(5, 20.0)], np.c_[xs, np.full(5, 40.0)]])  # 20 px apart

    def column(keep_rows):
        out = np.full((60, 100, 3), 128, np.uint8)
        mouth.draw(out, np.ones((60, 100), np.float32), image, curves, gap=10.0, keep_rows=keep_rows)
        return out[:, 45:56].astype(float).mean(axis=(1, 2))

    kept, stretched = column(True), column(False)
    assert kept[24] > 215 and kept[30:40].max() < 40
    assert stretched[34:40].max() > 215 and stretched[30] < 40  # teeth, dark, teeth: what keep_rows avoids


def test_a_dark_gap_is_where_the_drivers_interior_parts():
    """dark_row: the upper teeth's edge over a black gap (row 20 of 32 black, the rest white) parts at
    the gap; teeth closed edge to edge (white over light grey, 200, no row under half the median), a
    tongue or a mouth dark throughout have none, and are drawn the photos' way."""
    image = np.full((32, 64, 3), 255, np.float32)
    image[20] = 0
    assert mouth.dark_row(image) == 20
    image[20] = 200
    image[16:] = 200
    assert mouth.dark_row(image) is None
    assert mouth.dark_row(np.full((32, 64, 3), 20, np.float32)) is None


def test_corner_inset_is_the_inner_corners_share_of_the_width_in_from_the_outer():
    """Outer corners 100 px apart, the inner ones 8 and 12 px in (and off the line: only the part
    along it counts): insets 0.08 and 0.12; 68 landmarks give the same."""
    outer = np.array([[10.0, 50.0], [110.0, 50.0]])
    inner = np.array([[18.0, 53.0], [98.0, 47.0]])
    np.testing.assert_allclose(mouth.corner_inset(outer, inner), [0.08, 0.12])
    lm = np.zeros((68, 2))
    lm[[48, 54]], lm[[60, 64]] = outer, inner
    np.testing.assert_allclose(mouth.landmark_inset(lm[None]), [[0.08, 0.12]])


def test_the_frames_inner_corners_move_in_as_far_as_the_drivers_do():
    """B's neutral insets 0.07, the driver's 0.08 at rest and 0.11 / 0.10 in a round "O" (its inner
    corners 3 and 2 % of its width further in): B's are 0.10 and 0.09; placed on a mouth whose outer
    corners are 80 px apart (tilted), each corner lies that share of the way in, its offset across
    the mouth kept. A missing point gives None."""
    lm = np.zeros((68, 2))
    lm[[48, 54]] = [[0.0, 0.0], [100.0, 0.0]]
    lm[[60, 64]] = [[11.0, 1.0], [90.0, 1.0]]
    insets = mouth.frame_insets(np.array([0.07, 0.07]), np.array([0.08, 0.08]), lm)
    np.testing.assert_allclose(insets, [0.10, 0.09])
    angle = np.deg2rad(10.0)
    axis = 80.0 * np.array([np.cos(angle), np.sin(angle)])
    across = np.array([-np.sin(angle), np.cos(angle)])
    outer = np.array([[20.0, 30.0], [20.0, 30.0] + axis])
    curves = np.zeros((2, 5, 2))
    curves[:, :, :] = outer[0] + np.linspace(0.02, 0.98, 5)[:, None] * axis  # corners where a mesh left them
    curves[:, 0] += 1.5 * across
    placed = mouth.place_corners(curves, outer, insets)
    np.testing.assert_allclose(placed[:, 0], [outer[0] + 0.10 * axis + 1.5 * across] * 2, atol=1e-9)
    np.testing.assert_allclose(placed[:, -1], [outer[1] - 0.09 * axis] * 2, atol=1e-9)
    np.testing.assert_array_equal(placed[:, 1:-1], curves[:, 1:-1])  # the other nodes stay
    lm[60] = np.nan
    assert mouth.frame_insets(np.array([0.07, 0.07]), np.array([0.08, 0.08]), lm) is None


def test_the_lower_lips_shadow_darkens_a_band_above_it_a_tenth_of_the_gap():
    """A grey interior (200) drawn as the driver's own between lips 30 px apart (rows 20 to 50) with the
    lower lip's shadow at 0.5: the last whole pixel above the lip (1 to 2 px up, where the factor is
    0.58-0.70) is under 0.75 of the grey and no darker than half of it; 7 px up it is within 5 % of the
    grey, and the upper half is untouched. With no shadow the gap is grey to the lip. A gap 1 px tall is
    untouched within a grey level (0.3 %)."""
    image = np.full((32, 64, 3), 200, np.float32)
    xs = np.linspace(20, 80, 5)

    def column(top, bottom, shadow):
        curves = np.stack([np.c_[xs, np.full(5, top)], np.c_[xs, np.full(5, bottom)]])
        out = np.full((70, 100, 3), 128, np.uint8)
        mouth.draw(out, np.ones((70, 100), np.float32), image, curves, gap=30.0, keep_rows=True, shadow=shadow)
        return out[:, 45:56].astype(float).mean(axis=(1, 2))

    shaded, plain = column(20.0, 50.0, 0.5), column(20.0, 50.0, 0.0)
    assert np.allclose(plain[21:50], 200, atol=1)
    assert 100 <= shaded[49] < 150
    assert shaded[43] > 190 and np.allclose(shaded[21:35], 200, atol=1)
    thin = column(30.0, 31.0, 0.5)
    assert abs(thin[30] - column(30.0, 31.0, 0.0)[30]) <= 1
    assert np.allclose(mouth.lower_lip_shadow(4, 0.0), 1)


def test_the_built_in_mouth_backend_is_the_median_of_the_widest_and_darkest_and_the_teeth_share():
    """The ``mouth`` kind's default (plugins/builtin/mouth.py) makes the interiors, their gaps and B's lips with
    the functions here, as the render's mouth settings say, reading only the open photos; its cache key is the
    mouth stage's before the kind existed: "-" and version 2."""
    from persona.plugins.builtin.mouth import MedianMouth
    from persona.plugins.face.dynamics import smooth_in_time
    from persona.plugins.kinds import MouthPhotos
    from persona.plugins.manager import default_registry

    assert default_registry().default("mouth") == "median"
    assert (MedianMouth.key_name, MedianMouth.version) == ("-", "2")
    photos = [open_photo(g) for g in (4.0, 20.0, 0.0, 12.0, 16.0)]
    photos[4][0][100:120] = 40  # the darkest of the open ones
    points = np.stack([p[1] for p in photos])
    read = []

    class Lazy(list):
        def __getitem__(self, i):
            read.append(i)
            return super().__getitem__(i)

    made = MedianMouth().interior(MouthPhotos(Lazy(p[0] for p in photos), points, points), count=2, min_gap=0.05,
                                  choice="driver")
    assert sorted(read) == [0, 1, 3, 4]  # the photo with closed lips is not read
    samples = {i: mouth.sample(photos[i][0], points[i]) for i in (1, 4, 3, 0)}  # widest first
    order = list(samples)
    darkest = [order[k] for k in mouth.darkest(np.stack(list(samples.values())), 2)]
    for interior, chosen in ((made.interior, [1, 4]), (made.cavity, darkest)):
        expected = mouth.interior(samples[i] for i in chosen).round().astype(np.uint8)
        np.testing.assert_array_equal(interior.image, expected)
        assert interior.gap == np.nanmedian(mouth.lip_gap(points[chosen], per_iod=False))
    np.testing.assert_array_equal(made.lips, mouth.lip_curves(points.mean(axis=0)))
    assert MedianMouth().interior(MouthPhotos(Lazy(p[0] for p in photos), points, points), count=2,
                                  min_gap=0.05, choice="widest").cavity is None
    frames = [(image, lm) for image, lm in photos]
    shares = [mouth.teeth_share(image, lm) for image, lm in frames]
    np.testing.assert_array_equal(MedianMouth().teeth(iter(frames), 1.5), smooth_in_time(np.array(shares), 1.5))


def test_curves_a_texel_apart_are_read_on_each_side_of_the_lips_line():
    """A puppet whose photos never part their lips has inner-lip curves about half a texel apart; the
    renderer reads the mesh for them at least LIP_SIDES texels apart, each lip by half the shortfall, the
    corners (shared by both curves) as they are; curves further apart stay where they are."""
    xs = np.linspace(60, 130, 5)
    closed = np.stack([np.c_[xs, [170, 169.8, 169.7, 169.8, 170]], np.c_[xs, [170, 170.3, 170.3, 170.3, 170]]])
    read = mouth.apart(closed)
    np.testing.assert_allclose(read[1, 1:-1, 1] - read[0, 1:-1, 1], mouth.LIP_SIDES)
    np.testing.assert_allclose((read[0, 1:-1, 1] + read[1, 1:-1, 1]) / 2, (closed[0, 1:-1, 1] + closed[1, 1:-1, 1]) / 2)
    np.testing.assert_array_equal(read[:, [0, -1]], closed[:, [0, -1]])
    np.testing.assert_array_equal(read[..., 0], closed[..., 0])
    opened = closed.copy()
    opened[1, 1:-1, 1] += 6
    np.testing.assert_array_equal(mouth.apart(opened), opened)
