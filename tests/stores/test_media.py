"""Tests for persona.stores.media: every way a photo, a video or a sidecar can go wrong."""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import resource
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps

import badinput
from persona.stores import media
from persona.stores.errors import InputError, PersonaError
from persona.stores.media import PhotoRejected, Source

REAL_VIDEO = Path(__file__).resolve().parents[3] / "shared" / "data" / "videos" / "obama_address.mov"


def synthetic_face(h: int = 120, w: int = 90, seed: int = 0) -> np.ndarray:
    """A smooth, non-square, asymmetric RGB picture (JPEG-friendly, orientation-revealing)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:h, :w].astype(np.float64)
    r = 40 + 180 * x / w
    g = 30 + 200 * y / h
    b = 128 + 60 * np.sin(x / 9 + seed) * np.cos(y / 13)
    img = np.dstack([r, g, b])
    cy, cx = h * 0.35, w * 0.3  # a dark blob off-centre: any flip or rotation moves it
    img[(y - cy) ** 2 + (x - cx) ** 2 < (min(h, w) * 0.12) ** 2] = rng.integers(0, 40, 3)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def faces():
    return [synthetic_face(seed=i) for i in range(3)]


@pytest.fixture(scope="module")
def bad(tmp_path_factory, faces):
    folder = tmp_path_factory.mktemp("bad")
    expected = badinput.make_bad_collection(folder, faces)
    return folder, expected


def mad(a, b) -> float:
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).mean())


def maxdiff(a, b) -> int:
    return int(np.abs(a.astype(np.int32) - b.astype(np.int32)).max())


# --------------------------------------------------------------------------- decode


def test_bad_collection_outcomes(bad):
    folder, expected = bad
    assert len(expected) >= 10
    assert sorted(p.name for p in folder.iterdir()) == sorted(expected)
    for name, outcome in expected.items():
        if outcome == "ok":
            a = media.decode_image(folder / name)
            assert a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3, name
            assert a.flags.c_contiguous, name
        else:
            with pytest.raises(PhotoRejected) as ei:
                media.decode_image(folder / name)
            assert outcome in ei.value.reason, (name, ei.value.reason)


@pytest.mark.parametrize(
    "name, reason",
    [
        ("corrupt.jpg", "corrupt or truncated JPEG: "),
        ("notes.jpg", "not an image (cannot identify image file)"),
        ("empty.jpg", "empty file (0 bytes)"),
        ("tiny.png", "too small: 1x1 px (minimum 32 px a side)"),
    ],
)
def test_rejection_reasons_are_specific(bad, name, reason):
    folder, _ = bad
    with pytest.raises(PhotoRejected) as ei:
        media.decode_image(folder / name)
    assert ei.value.reason.startswith(reason)
    assert str(ei.value) == ei.value.reason


def test_probe_rejects_header_level_problems(bad):
    folder, _ = bad
    for name, word in [("notes.jpg", "not an image"), ("empty.jpg", "empty"), ("tiny.png", "too small")]:
        with pytest.raises(PhotoRejected, match=word):
            media.probe_image(folder / name)
    # a truncated body has a fine header: probe passes, decode rejects
    assert media.probe_image(folder / "corrupt.jpg") == media.ImageInfo(90, 120)


def test_missing_file_and_folder_are_rejected(tmp_path):
    with pytest.raises(PhotoRejected, match="file not found"):
        media.decode_image(tmp_path / "nope.jpg")
    with pytest.raises(PhotoRejected, match="not an image"):
        media.decode_image(tmp_path)


def test_truncated_png_is_corrupt(tmp_path, faces):
    buf = io.BytesIO()
    Image.fromarray(faces[0]).save(buf, format="PNG")
    (tmp_path / "cut.png").write_bytes(buf.getvalue()[: len(buf.getvalue()) // 2])
    with pytest.raises(PhotoRejected, match="corrupt or truncated PNG"):
        media.decode_image(tmp_path / "cut.png")


def test_good_jpeg_decodes_to_the_picture(bad, faces):
    folder, _ = bad
    a = media.decode_image(folder / "good.jpg")
    assert a.shape == faces[0].shape
    assert mad(a, faces[0]) < 2.0


def test_16bit_rgb_png_equals_8bit(bad, faces):
    folder, _ = bad
    a = media.decode_image(folder / "sixteen_bit.png")
    assert a.shape == faces[0].shape
    assert maxdiff(a, faces[0]) <= 1


def test_16bit_is_rounded_not_truncated(tmp_path, faces):
    # v = 257 x + 128 must come back as x (round(v / 257)); keeping the high byte gives x + 1
    v = faces[0].astype(np.uint16) * 257 + 128
    cv2.imwrite(str(tmp_path / "rgb16.png"), v[..., ::-1])
    assert maxdiff(media.decode_image(tmp_path / "rgb16.png"), faces[0]) == 0
    # 16-bit grey (Pillow mode I;16) and 16-bit RGBA
    cv2.imwrite(str(tmp_path / "grey16.png"), v[..., 0])
    g = media.decode_image(tmp_path / "grey16.png")
    assert maxdiff(g, np.repeat(faces[0][..., :1], 3, axis=2)) == 0
    rgba16 = np.dstack([v[..., ::-1], np.full(v.shape[:2], 65535, np.uint16)])
    cv2.imwrite(str(tmp_path / "rgba16.png"), rgba16)
    assert maxdiff(media.decode_image(tmp_path / "rgba16.png"), faces[0]) == 0
    # 16-bit TIFF
    cv2.imwrite(str(tmp_path / "rgb16.tif"), v[..., ::-1])
    assert maxdiff(media.decode_image(tmp_path / "rgb16.tif"), faces[0]) == 0


def test_exif_rotated_jpeg_decodes_upright(bad, faces):
    folder, _ = bad
    raw = np.asarray(Image.open(folder / "rotated.jpg"))
    assert raw.shape[:2] == (90, 120)  # the stored pixels really are rotated
    a = media.decode_image(folder / "rotated.jpg")
    assert a.shape == faces[0].shape
    assert mad(a, faces[0]) < 2.0
    assert media.probe_image(folder / "rotated.jpg") == media.ImageInfo(width=90, height=120)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_exif_orientation_matches_pillow(tmp_path, faces, orientation):
    path = tmp_path / f"o{orientation}.jpg"
    badinput.exif_rotated_jpeg(path, faces[1], orientation)
    with Image.open(path) as im:
        want = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    got = media.decode_image(path)
    assert np.array_equal(got, want)
    assert mad(got, faces[1]) < 2.0
    info = media.probe_image(path)
    assert (info.height, info.width) == faces[1].shape[:2]


def test_rgba_is_composited_over_mid_grey(bad, faces):
    folder, _ = bad
    a = media.decode_image(folder / "rgba.png")
    face = faces[2]
    assert np.array_equal(a[4:-4, 4:-4], face[4:-4, 4:-4])  # opaque: untouched
    want = np.rint(face.astype(np.float64) * 64 / 255 + 128 * (1 - 64 / 255))
    assert maxdiff(a[:4], want[:4]) <= 1
    assert maxdiff(a[:, -4:], want[:, -4:]) <= 1


def test_grayscale_gives_three_equal_channels(bad, faces):
    folder, _ = bad
    a = media.decode_image(folder / "gray.jpg")
    assert a.shape == faces[1].shape
    assert np.array_equal(a[..., 0], a[..., 1]) and np.array_equal(a[..., 1], a[..., 2])
    want = np.asarray(Image.fromarray(faces[1]).convert("L"))
    assert mad(a[..., 0], want) < 2.0


def test_palette_png(bad, faces):
    folder, _ = bad
    a = media.decode_image(folder / "palette.png")
    assert mad(a, faces[1]) < 4.0


def test_palette_transparency_and_la_and_1bit_and_cmyk(tmp_path, faces):
    # palette with a transparent index that is used: those pixels become grey 128
    p = Image.new("P", (40, 40), 1)
    p.putpalette([0, 0, 0, 255, 0, 0] + [0] * (254 * 3))
    p.paste(0, (0, 0, 10, 40))
    p.save(tmp_path / "ptrans.png", transparency=0)
    a = media.decode_image(tmp_path / "ptrans.png")
    assert (a[:, :10] == 128).all() and (a[:, 10:] == [255, 0, 0]).all()
    # palette with per-entry alpha bytes (the case Pillow warns about on a naive convert)
    p.save(tmp_path / "pbytes.png", transparency=bytes([0, 255] + [255] * 254))
    a = media.decode_image(tmp_path / "pbytes.png")
    assert (a[:, :10] == 128).all() and (a[:, 10:] == [255, 0, 0]).all()
    # LA: alpha 0 -> grey
    la = np.dstack([np.full((40, 40), 200, np.uint8), np.zeros((40, 40), np.uint8)])
    la[:, 20:, 1] = 255
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    a = media.decode_image(tmp_path / "la.png")
    assert (a[:, :20] == 128).all() and (a[:, 20:] == 200).all()
    # 1-bit
    Image.fromarray(np.eye(40, dtype=bool)).save(tmp_path / "bw.png")
    a = media.decode_image(tmp_path / "bw.png")
    assert a.shape == (40, 40, 3) and set(np.unique(a)) == {0, 255}
    # CMYK JPEG
    Image.fromarray(faces[0]).convert("CMYK").save(tmp_path / "cmyk.jpg", quality=95)
    a = media.decode_image(tmp_path / "cmyk.jpg")
    assert a.shape == faces[0].shape and mad(a, faces[0]) < 4.0


def test_downscale_keeps_aspect_and_uses_area(tmp_path):
    big = cv2.resize(synthetic_face(), (2400, 3200), interpolation=cv2.INTER_CUBIC)
    Image.fromarray(big).save(tmp_path / "big.png")
    a = media.decode_image(tmp_path / "big.png", max_side=400)
    assert a.shape == (400, 300, 3)
    assert mad(a, cv2.resize(big, (300, 400), interpolation=cv2.INTER_AREA)) < 0.5
    # JPEG: DCT-domain pre-shrink (draft) + INTER_AREA stays close to full decode + INTER_AREA
    Image.fromarray(big).save(tmp_path / "big.jpg", quality=95)
    a = media.decode_image(tmp_path / "big.jpg", max_side=400)
    assert a.shape == (400, 300, 3)
    full = np.asarray(Image.open(tmp_path / "big.jpg").convert("RGB"))
    assert mad(a, cv2.resize(full, (300, 400), interpolation=cv2.INTER_AREA)) < 2.0
    # never upscales
    assert media.decode_image(tmp_path / "big.png", max_side=10_000).shape == big.shape


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


@pytest.mark.parametrize(
    "size, reason",
    [
        ((30000, 30000), "decompression bomb: header claims 900 MP"),  # Pillow's limit fires first
        ((9000, 8000), "decompression bomb: 9000x8000 = 72 MP exceeds max_pixels 64 MP"),
    ],
)
def test_decompression_bomb_rejected_from_header(tmp_path, size, reason):
    path = badinput.make_bomb_png(tmp_path / "bomb.png", *size)
    assert path.stat().st_size < 200
    before = _maxrss_mb()
    for fn in (media.decode_image, media.probe_image):
        with pytest.raises(PhotoRejected) as ei:
            fn(path)
        assert ei.value.reason.startswith(reason), ei.value.reason
    assert _maxrss_mb() - before < 50  # nothing the size of the claimed image was allocated


def test_max_pixels_and_min_side_are_parameters(bad):
    folder, _ = bad
    with pytest.raises(PhotoRejected, match=r"decompression bomb: 90x120 = .* exceeds max_pixels"):
        media.decode_image(folder / "good.jpg", max_pixels=5000)
    with pytest.raises(PhotoRejected, match=r"too small: 90x120 px \(minimum 100 px a side\)"):
        media.probe_image(folder / "good.jpg", min_side=100)


def test_photo_rejected_pickles():
    e = pickle.loads(pickle.dumps(PhotoRejected("empty file (0 bytes)")))
    assert isinstance(e, PhotoRejected) and e.reason == "empty file (0 bytes)"


def test_sha256_file(tmp_path):
    data = os.urandom(3 << 20)
    (tmp_path / "x.bin").write_bytes(data)
    assert media.sha256_file(tmp_path / "x.bin") == hashlib.sha256(data).hexdigest()


# --------------------------------------------------------------------------- sources


def test_is_video():
    assert media.is_video("a/b.MP4") and media.is_video("x.mov") and media.is_video(Path("y.webm"))
    assert not media.is_video("x.jpg") and not media.is_video("mp4")


def _touch(folder: Path, *names: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"x")


def test_resolve_folder_sorted_nonrecursive_hidden_skipped(tmp_path):
    _touch(tmp_path / "photos", "b.jpg", "a.png", "notes.txt", ".DS_Store", "c.JPG")
    _touch(tmp_path / "photos" / "sub", "z.jpg")
    srcs = media.resolve_sources("photos", tmp_path)
    assert [s.id for s in srcs] == ["a", "b", "c", "notes", "sub"]  # the sub-folder a photo to reject, not opened
    assert all(Path(s.path).is_absolute() and s.frame is None for s in srcs)
    assert srcs[0] == Source(id="a", path=str(tmp_path / "photos" / "a.png"), frame=None)


def test_resolve_glob_list_single_file_and_duplicate_stems(tmp_path):
    _touch(tmp_path / "a", "x.jpg", "y.jpg", "y.txt")
    _touch(tmp_path / "b", "x.png")
    assert [s.id for s in media.resolve_sources("a/*.jpg", tmp_path)] == ["x", "y"]
    assert [s.id for s in media.resolve_sources("a/[x]*", tmp_path)] == ["x"]
    srcs = media.resolve_sources(["a/x.jpg", str(tmp_path / "b"), "a/*.txt"], tmp_path)
    assert [s.id for s in srcs] == ["x", "x_2", "y"]
    assert [Path(s.path).parent.name for s in srcs] == ["a", "b", "a"]
    # the same file reached twice is listed once
    srcs = media.resolve_sources(["a", "a/*.jpg"], tmp_path)
    assert [s.id for s in srcs] == ["x", "y", "y_2"]
    assert len({s.path for s in srcs}) == 3
    # absolute paths ignore base_dir; Path objects are accepted
    assert media.resolve_sources(tmp_path / "b" / "x.png", "/nonexistent")[0].id == "x"


def test_resolve_errors_name_the_path(tmp_path):
    (tmp_path / "empty").mkdir()
    _touch(tmp_path / "hidden_only", ".a.jpg")
    cases = [
        ("missing_folder", "does not exist"),
        ("missing.jpg", "does not exist"),
        ("empty", "is empty"),
        ("hidden_only", "is empty"),
        ("empty/*.jpg", "matches no files"),
    ]
    for spec, words in cases:
        with pytest.raises(InputError) as ei:
            media.resolve_sources(spec, tmp_path)
        msg = str(ei.value)
        assert spec in msg and words in msg, msg
        assert isinstance(ei.value, (PersonaError, ValueError))
    with pytest.raises(InputError, match="empty"):
        media.resolve_sources([], tmp_path)
    with pytest.raises(InputError, match="cannot use 3"):
        media.resolve_sources([3], tmp_path)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 20-frame 64x48 clip at 25 fps: a white square moving right, frame index in red."""
    frames = []
    for i in range(20):
        a = np.full((48, 64, 3), 40, np.uint8)
        a[10:26, 2 + 2 * i : 18 + 2 * i] = 255
        a[36:, :, 0] = 10 * i
        frames.append(a)
    path = tmp_path_factory.mktemp("video") / "clip.mp4"
    media.write_video_mp4(path, frames, fps=25)
    return path, frames


def test_resolve_video_and_frame_range(clip, tmp_path):
    path, frames = clip
    srcs = media.resolve_sources(str(path), tmp_path)
    assert len(srcs) == 20
    assert srcs[0] == Source(id="frame000000", path=str(path), frame=0)
    assert srcs[-1].id == "frame000019"
    srcs = media.resolve_sources({"video": str(path), "start": 3, "stop": 12, "step": 4}, tmp_path)
    assert [s.frame for s in srcs] == [3, 7, 11]
    assert [s.id for s in srcs] == ["frame000003", "frame000007", "frame000011"]
    srcs = media.resolve_sources({"video": str(path), "start": 15, "stop": 1000}, tmp_path)
    assert [s.frame for s in srcs] == list(range(15, 20))
    # relative video path, and two ranges of the same video do not repeat frames
    rel = os.path.relpath(path, tmp_path)
    srcs = media.resolve_sources([{"video": rel, "stop": 2}, {"video": rel, "start": 1, "stop": 3}], tmp_path)
    assert [s.frame for s in srcs] == [0, 1, 2]


def test_resolve_frame_range_errors(clip, tmp_path):
    path, _ = clip
    for spec, words in [
        ({"video": str(path), "start": 20}, "selects no frames"),
        ({"video": str(path), "step": 0}, "'step' must be >= 1"),
        ({"video": str(path), "start": "3"}, "'start' must be an integer"),
        ({"video": str(path), "stpo": 3}, "unknown key"),
        ({"start": 3}, "missing key 'video'"),
        ({"video": "nope.mp4"}, "does not exist"),
    ]:
        with pytest.raises(InputError, match=words):
            media.resolve_sources(spec, tmp_path)


# --------------------------------------------------------------------------- video


def test_video_roundtrip(clip):
    path, frames = clip
    with media.VideoReader(path) as r:
        assert r.n_frames == 20
        assert r.fps == 25.0
        assert (r.width, r.height) == (64, 48)
        got = list(r.frames())
        assert [i for i, _ in got] == list(range(20))
        for (i, a), want in zip(got, frames):
            assert a.shape == (48, 64, 3) and a.dtype == np.uint8 and a.flags.c_contiguous
            assert mad(a, want) < 3.0, i
        # exact indices for ranges, decoding from the start each time
        sub = list(r.frames(start=5, stop=14, step=3))
        assert [i for i, _ in sub] == [5, 8, 11]
        assert np.array_equal(sub[1][1], got[8][1])
        assert list(r.frames(start=25)) == []


def test_video_writer_pads_odd_sizes_and_keeps_ntsc_rate(tmp_path):
    frames = [np.full((47, 63), 30 * i, np.uint8) for i in range(5)]  # grey, odd size
    out = tmp_path / "sub" / "odd.mp4"
    media.write_video_mp4(out, frames, fps=30000 / 1001)
    assert sorted(p.name for p in out.parent.iterdir()) == ["odd.mp4"]  # no temp left
    with media.VideoReader(out) as r:
        assert (r.width, r.height) == (64, 48)
        assert abs(r.fps - 29.97) < 0.01
        assert r.n_frames == 5
        for (i, a), want in zip(r.frames(), frames):
            assert mad(a[:47, :63, 0], want) < 3.0


def test_video_writer_keeps_colours(tmp_path):
    """Saturated and skin colours and a grey ramp come back as written (BT.601 video range both ways, as
    players assume): the mean of each 16 x 16 patch within 3 levels in every channel."""
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (224, 172, 140), (120, 80, 60),
               (0, 0, 0), (64, 64, 64), (128, 128, 128), (192, 192, 192), (255, 255, 255), (30, 200, 180)]
    frame = np.zeros((48, 64, 3), np.uint8)
    for k, c in enumerate(colours):
        frame[16 * (k // 4):16 * (k // 4 + 1), 16 * (k % 4):16 * (k % 4 + 1)] = c
    path = tmp_path / "colours.mp4"
    media.write_video_mp4(path, [frame] * 3, fps=25)
    with media.VideoReader(path) as r:
        _, got = next(iter(r.frames()))
    for k, c in enumerate(colours):
        patch = got[16 * (k // 4) + 4:16 * (k // 4 + 1) - 4, 16 * (k % 4) + 4:16 * (k % 4 + 1) - 4]
        assert np.abs(patch.reshape(-1, 3).mean(0) - c).max() < 3, (c, patch.reshape(-1, 3).mean(0))


def test_video_writer_rejects_bad_input_and_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        media.write_video_mp4(tmp_path / "a.mp4", [], fps=25)
    with pytest.raises(ValueError, match="expected 64x48"):
        media.write_video_mp4(tmp_path / "b.mp4", [np.zeros((48, 64, 3), np.uint8), np.zeros((40, 64, 3), np.uint8)], 25)
    with pytest.raises(TypeError, match="uint8"):
        media.write_video_mp4(tmp_path / "c.mp4", [np.zeros((48, 64, 3), np.float32)], 25)
    with pytest.raises(ValueError, match="fps"):
        media.write_video_mp4(tmp_path / "d.mp4", [np.zeros((48, 64, 3), np.uint8)], 0)
    assert list(tmp_path.iterdir()) == []


def test_video_display_rotation_is_applied(tmp_path):
    import av

    a = np.zeros((48, 64, 3), np.uint8)
    a[:10, :20] = 255  # top-left marker
    path = tmp_path / "rot.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        s.set_display_rotation(90)  # counter-clockwise, as FFmpeg's display matrix says
        for i in range(3):
            f = av.VideoFrame.from_ndarray(a, format="rgb24")
            f.pts = i
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode(None):
            c.mux(p)
    with media.VideoReader(path) as r:
        assert (r.width, r.height) == (48, 64)
        frames = list(r.frames())
    assert len(frames) == 3
    assert frames[0][1].shape == (64, 48, 3)
    assert mad(frames[0][1], np.rot90(a, 1)) < 3.0  # marker now bottom-left


def test_broken_videos_raise_input_error_naming_the_file(tmp_path, clip, bad):
    path, _ = clip
    cases = {
        "garbage.mp4": os.urandom(5000),
        "empty.mp4": b"",
        "text.mov": b"this is not a video\n" * 50,
        "truncated.mp4": path.read_bytes()[:300],
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    for name in [*cases, "missing.mp4"]:
        with pytest.raises(InputError) as ei:
            media.VideoReader(tmp_path / name)
        assert name in str(ei.value), str(ei.value)
    folder, _ = bad
    with pytest.raises(InputError, match="still image"):
        media.VideoReader(folder / "good.jpg")
    # resolve_sources passes the error on
    with pytest.raises(InputError, match="garbage.mp4"):
        media.resolve_sources("garbage.mp4", tmp_path)


@pytest.mark.realdata
@pytest.mark.skipif(not REAL_VIDEO.is_file(), reason="../shared/data is absent")
def test_real_video_frame_count_is_exact():
    with media.VideoReader(REAL_VIDEO) as r:
        assert r.fps == 25.0
        assert (r.width, r.height) == (256, 256)
        assert r.n_frames == 1169
        n = 0
        for i, a in r.frames():
            assert i == n and a.shape == (256, 256, 3)
            n += 1
        assert n == 1169 and r.n_frames == 1169
        last = list(r.frames(start=1168))
        assert [i for i, _ in last] == [1168]


# --------------------------------------------------------------------------- landmarks


def test_pts_round_trip(tmp_path):
    img = tmp_path / "face.jpg"
    assert media.read_landmark_sidecar(img) is None
    xy = np.random.default_rng(0).uniform(0, 250, (68, 2))
    out = media.write_landmark_sidecar(img, xy)
    assert out == tmp_path / "face.pts"
    text = out.read_text().splitlines()
    assert text[:3] == ["version: 1", "n_points: 68", "{"] and text[-1] == "}"
    back = media.read_landmark_sidecar(img)
    assert back.dtype == np.float64 and back.shape == (68, 2)
    assert np.array_equal(back, xy)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["face.pts"]


def test_pts_malformed(tmp_path):
    img = tmp_path / "foo.png"
    good = ["version: 1", "n_points: 68", "{", *["1.5 2.5"] * 68, "}"]
    bad_files = {
        "missing brace": good[:3] + good[3:-1],
        "67 points": good[:3] + good[4:],
        "wrong n_points": ["version: 1", "n_points: 49", "{", *["1 2"] * 49, "}"],
        "not a number": good[:3] + ["1.5 abc"] + good[4:],
        "three numbers": good[:3] + ["1 2 3"] + good[4:],
        "nan": good[:3] + ["nan 2"] + good[4:],
        "no header": good[2:],
    }
    for what, lines in bad_files.items():
        (tmp_path / "foo.pts").write_text("\n".join(lines))
        with pytest.raises(PhotoRejected) as ei:
            media.read_landmark_sidecar(img)
        assert ei.value.reason.startswith("bad landmark sidecar foo.pts: "), (what, ei.value.reason)
    (tmp_path / "foo.pts").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(PhotoRejected, match="bad landmark sidecar foo.pts"):
        media.read_landmark_sidecar(img)
    with pytest.raises(ValueError, match="shape"):
        media.write_landmark_sidecar(img, np.zeros((49, 2)))


# --------------------------------------------------------------------------- outputs


def test_write_png_atomic_round_trip(tmp_path, faces):
    out = tmp_path / "deep" / "er" / "x.png"
    media.write_png(out, faces[0])
    assert np.array_equal(np.asarray(Image.open(out)), faces[0])
    media.write_png(out, faces[1][..., 0])  # overwrite, grey
    with Image.open(out) as im:
        assert im.mode == "L" and np.array_equal(np.asarray(im), faces[1][..., 0])
    assert sorted(p.name for p in out.parent.iterdir()) == ["x.png"]
    with pytest.raises(TypeError):
        media.write_png(tmp_path / "f.png", faces[0].astype(np.float32))
    with pytest.raises(ValueError):
        media.write_png(tmp_path / "g.png", np.zeros((4, 4, 4), np.uint8))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["deep"]


def test_write_png_leaves_no_temp_on_failure(tmp_path, faces, monkeypatch):
    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(media.os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        media.write_png(tmp_path / "x.png", faces[0])
    assert list(tmp_path.iterdir()) == []


def test_contact_sheet(faces):
    tiles = [np.full((10, 8, 3), i * 20, np.uint8) for i in range(7)] + [np.full((10, 8), 250, np.uint8)]
    sheet = media.contact_sheet(tiles, columns=3, gap=2, background=255)
    assert sheet.shape == (3 * 10 + 2 * 2, 3 * 8 + 2 * 2, 3) and sheet.dtype == np.uint8
    assert (sheet[0:10, 0:8] == 0).all()
    assert (sheet[0:10, 10:18] == 20).all()
    assert (sheet[12:22, 0:8] == 60).all()
    assert (sheet[24:34, 10:18] == 250).all()  # grey tile promoted
    assert (sheet[:, 8:10] == 255).all() and (sheet[24:34, 20:28] == 255).all()  # gap, empty cell
    one = media.contact_sheet([faces[0]], columns=10)
    assert np.array_equal(one, faces[0])
    with pytest.raises(ValueError, match="expected"):
        media.contact_sheet([faces[0], faces[0][:50]])
    with pytest.raises(ValueError, match="no images"):
        media.contact_sheet([])


# --------------------------------------------------------------------------- more decode corners


def test_png_exif_orientation_and_probe_reads_header_only(tmp_path, faces):
    exif = Image.Exif()
    exif[badinput.EXIF_ORIENTATION] = 8
    Image.fromarray(np.ascontiguousarray(np.rot90(faces[0], -1))).save(tmp_path / "o8.png", exif=exif.tobytes())
    assert np.array_equal(media.decode_image(tmp_path / "o8.png"), faces[0])
    assert media.probe_image(tmp_path / "o8.png") == media.ImageInfo(width=90, height=120)
    # header only: a PNG cut after its header probes fine but does not decode
    data = (tmp_path / "o8.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 3])
    assert media.probe_image(tmp_path / "cut.png") == media.ImageInfo(width=90, height=120)
    with pytest.raises(PhotoRejected, match="corrupt or truncated PNG"):
        media.decode_image(tmp_path / "cut.png")


def test_broken_exif_does_not_reject_the_photo(tmp_path, faces):
    good = badinput.jpeg_bytes(faces[0])
    # splice an APP1 "Exif" segment holding garbage right after SOI
    payload = b"Exif\x00\x00" + b"MM\x00\x2a\xff\xff\xff\xff" + os.urandom(20)
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    (tmp_path / "badexif.jpg").write_bytes(good[:2] + app1 + good[2:])
    a = media.decode_image(tmp_path / "badexif.jpg")
    assert mad(a, faces[0]) < 2.0


def test_decoding_in_threads_restores_warning_filters(bad):
    import warnings
    from concurrent.futures import ThreadPoolExecutor

    folder, expected = bad
    before = list(warnings.filters)

    def work(name):
        try:
            return media.decode_image(folder / name).shape
        except PhotoRejected as e:
            return e.reason

    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(work, list(expected) * 20))
    assert len(results) == 20 * len(expected)
    assert warnings.filters == before
    assert media._quiet_depth == 0


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_outputs_get_the_mode_of_any_new_file(tmp_path, faces, monkeypatch, umask):
    """Outputs are written to a private temporary file and renamed: they must end with the mode a
    new file gets under the umask (0644 under 022), not the temporary file's 0600, or nobody else on
    a shared machine or a web server can read them."""
    monkeypatch.setattr(media, "_UMASK", umask)
    media.write_png(tmp_path / "a.png", faces[0])
    media.write_video_mp4(tmp_path / "a.mp4", [faces[0]] * 2, 25)
    for name in ("a.png", "a.mp4"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name


def test_sound_is_carried_across_and_cut_to_a_frame_range(tmp_path):
    """A 4 s video whose sound is a tone rising in pitch: its frames 25-74 (1-3 s) re-encoded with
    the sound cut to the same range keep a sound stream exactly as long as the video, in sync with
    the source to within a millisecond; a second video written in the same pass carries the same
    sound; a video without sound has None."""
    rate, fps = 44100, 25
    t = np.arange(4 * rate) / rate
    tone = (0.5 * np.sin(2 * np.pi * (200 + 100 * t) * t)).astype(np.float32)
    frames = [np.full((32, 32, 3), i, np.uint8) for i in range(4 * fps)]
    source = tmp_path / "source.mp4"
    media.write_video_mp4(source, frames, fps, media.Audio(np.stack([tone, tone]), rate))
    whole = media.read_audio(source)
    assert whole.rate == rate and whole.samples.shape[0] == 2

    cut = media.read_audio(source, 25 / fps, 75 / fps)
    out, other = tmp_path / "cut.mp4", tmp_path / "other.mp4"
    media.write_videos_mp4([out, other], ((f, f[:16]) for f in frames[25:75]), fps, cut)
    import av

    with av.open(str(out)) as container:
        video, sound = container.streams.video[0], container.streams.audio[0]
        durations = [float(s.duration * s.time_base) for s in (video, sound)]
    assert abs(durations[0] - 2.0) < 1e-6 and abs(durations[1] - durations[0]) < 1 / fps, durations
    again = media.read_audio(out).samples[0]
    expected = tone[rate:3 * rate]
    probe = expected[rate // 2:rate // 2 + 4410]  # 0.1 s from the middle of the cut
    lag = int(np.argmax(np.correlate(again[:2 * rate], probe, mode="valid"))) - rate // 2
    assert abs(lag) <= rate // 1000, lag
    assert np.array_equal(media.read_audio(other).samples, media.read_audio(out).samples)  # encoded once, copied
    with media.VideoReader(other) as r:
        assert (r.width, r.height, r.n_frames) == (32, 16, 50)
    media.write_video_mp4(tmp_path / "silent.mp4", frames[:5], fps)
    assert media.read_audio(tmp_path / "silent.mp4") is None


def test_a_stray_video_in_a_folder_is_a_photo_to_reject_not_the_end_of_the_run(tmp_path, clip):
    """A file named like a video in a photo folder that does not open as one becomes a photo that
    ingest rejects with its reason; a real video there still gives its frames; the same broken file
    named on its own is still an error (the user asked for it)."""
    path, _ = clip
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(2):
        cv2.imwrite(str(folder / f"{i}.png"), np.zeros((64, 64, 3), np.uint8))
    (folder / "stray.mp4").write_bytes(os.urandom(3000))
    (folder / "real.mp4").write_bytes(path.read_bytes())
    sources = media.resolve_sources("photos", tmp_path)
    named = [(Path(s.path).name, s.frame) for s in sources]
    assert named[:2] == [("0.png", None), ("1.png", None)] and ("stray.mp4", None) in named
    assert sum(1 for name, frame in named if name == "real.mp4" and frame is not None) > 1
    with pytest.raises(PhotoRejected, match="not an image"):
        media.decode_image(folder / "stray.mp4")
    assert len(media.resolve_sources("photos/*.mp4", tmp_path)) == len(named) - 2  # a glob alike
    with pytest.raises(InputError, match="stray.mp4"):
        media.resolve_sources("photos/stray.mp4", tmp_path)


def test_a_folder_and_a_dangling_link_in_a_photo_folder_are_photos_rejected_with_their_reason(tmp_path):
    """A sub-folder and a link whose target is gone, in a photo folder: each is listed, so that
    ingest rejects it with a reason the user can act on, instead of passing over it in silence."""
    folder = tmp_path / "photos"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((64, 64, 3), np.uint8))
    (folder / "b.jpg").symlink_to(tmp_path / "gone" / "b.jpg")
    (folder / "thumbs").mkdir()
    sources = media.resolve_sources("photos", tmp_path)
    assert [s.id for s in sources] == ["a", "b", "thumbs"]
    with pytest.raises(PhotoRejected, match=r"a link to .*gone/b\.jpg, which does not exist"):
        media.decode_image(sources[1].path)
    with pytest.raises(PhotoRejected, match=r"not an image \(a folder\)"):
        media.decode_image(sources[2].path)


def test_a_folder_of_folders_is_an_empty_folder_naming_what_it_holds(tmp_path):
    """Pointed at the parent of photo folders: one clear error before any work, naming the
    sub-folders, rather than a photo rejected per sub-folder."""
    for name in ("bush", "powell"):
        (tmp_path / "people" / name).mkdir(parents=True)
    with pytest.raises(InputError, match=r"folder .*people\) is empty \(no visible files\) \(it holds only bush, "
                                         r"powell; sub-folders are not searched\)"):
        media.resolve_sources("people", tmp_path)
