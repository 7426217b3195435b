"""The generic 3D face: an analytic depth map with 68 landmarks, built by the project itself.

Nothing is downloaded (ALGORITHMS §3.1). The face is the analytic surface of ALGORITHMS §3.2,
re-anchored on a landmark layout measured from real photos:

* **Landmarks.** ``_LM68`` is the mean 68-point iBUG shape that dlib's predictor
  (``face_recognition_models``' ``shape_predictor_68_face_landmarks.dat``) returns on real
  near-frontal photos, printed by ``benchmarks/derive_template_landmarks.py``: dlib's HOG
  detector and the 68-point predictor ran over the LFW collections ``george_w_bush`` and
  ``colin_powell`` (766 photos, 765 detected). 175 near-frontal faces were kept: roll < 10°,
  nose tip within 0.06 inter-ocular distances of the eye midpoint, and nose-to-jaw-side
  distances within 10 % of each other. They were aligned by generalised Procrustes (translation,
  rotation, uniform scale). The mean was rotated so that the eyes are level, then scaled so
  that the eye centres (means of points 36-41 and 42-47) sit at ``X = -/+0.41, Y = -0.22`` (the
  spec's eye sockets). Last, the mean was averaged with its mirror image, with the iBUG indices
  swapped left/right.
* **Surface.** ``Z = 200 - h(X, Y)`` in canonical px, in the normalised coordinates
  ``X = (x - 97)/80, Y = (y - 112)/80``. ``h`` is a head ellipsoid plus Gaussian bumps and dents. Each
  feature is centred on the landmarks it belongs to: eye sockets on the eye centres, brow ridges
  just under the brow points, the nose tip on point 30, the alae inside 31/35, the lips on the
  mouth points, the chin above point 8, and the cheeks. The amplitudes are those of §3.2.
* **Mask.** The face oval is an ellipse fitted by least squares to the jaw contour (points 0-16):
  centre ``Y = -0.03``, semi-axes ``0.995`` and ``1.471``, largest radial residual 1.7 %. It is
  then enlarged by 3 %, so the jaw points lie just inside its boundary (1-4 px). Above the
  widest line the oval uses a shorter vertical semi-axis, so the forehead stays inside the
  194 x 244 frame.

Conventions (ALGORITHMS §0): ``x`` right, ``y`` down, pixel (row i, col j) centred at
``(x=j, y=i)``. Depth ``Z`` points away from the camera, so the nose tip has the smallest ``Z``.
Normals are ``n = (Z_x, Z_y, -1)/|.|`` and have ``n_z < 0``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

CANONICAL_HEIGHT = 244
CANONICAL_WIDTH = 194
CENTER_X = 97.0  # canonical x of X = 0
CENTER_Y = 112.0  # canonical y of Y = 0
UNIT = 80.0  # canonical px per normalised unit
BASE_DEPTH = 200.0  # Z = BASE_DEPTH - h

#: The 49 fiducials of SDM/IntraFace: iBUG 17..67 without the inner mouth corners 60 and 64.
IDX49: tuple[int, ...] = tuple(i for i in range(17, 68) if i not in (60, 64))

#: iBUG index of the mirror-image point (subject's right <-> left); MIRROR68[MIRROR68] = identity.
MIRROR68: tuple[int, ...] = tuple(
    list(range(16, -1, -1))
    + list(range(26, 16, -1))
    + [27, 28, 29, 30, 35, 34, 33, 32, 31]
    + [45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40]
    + [54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55]
    + [64, 63, 62, 61, 60, 67, 66, 65]
)

# Mean dlib 68-point shape on real near-frontal photos, normalised (X, Y); derived by
# benchmarks/derive_template_landmarks.py from 175 near-frontal LFW photos of
# george_w_bush and colin_powell (see the module docstring). Do not edit by hand.
_LM68 = np.array([
    [-0.9898, -0.2033],  # 0
    [-0.9777, +0.0624],  # 1
    [-0.9522, +0.3292],  # 2
    [-0.9122, +0.5911],  # 3
    [-0.8240, +0.8375],  # 4
    [-0.6751, +1.0550],  # 5
    [-0.4831, +1.2379],  # 6
    [-0.2595, +1.3903],  # 7
    [+0.0000, +1.4362],  # 8
    [+0.2595, +1.3903],  # 9
    [+0.4831, +1.2379],  # 10
    [+0.6751, +1.0550],  # 11
    [+0.8240, +0.8375],  # 12
    [+0.9122, +0.5911],  # 13
    [+0.9522, +0.3292],  # 14
    [+0.9777, +0.0624],  # 15
    [+0.9898, -0.2033],  # 16
    [-0.7828, -0.3465],  # 17
    [-0.6758, -0.4688],  # 18
    [-0.5094, -0.5104],  # 19
    [-0.3333, -0.4906],  # 20
    [-0.1627, -0.4340],  # 21
    [+0.1627, -0.4340],  # 22
    [+0.3333, -0.4906],  # 23
    [+0.5094, -0.5104],  # 24
    [+0.6758, -0.4688],  # 25
    [+0.7828, -0.3465],  # 26
    [+0.0000, -0.2483],  # 27
    [+0.0000, -0.0838],  # 28
    [+0.0000, +0.0764],  # 29
    [+0.0000, +0.2475],  # 30
    [-0.2002, +0.3596],  # 31
    [-0.1051, +0.3947],  # 32
    [+0.0000, +0.4263],  # 33
    [+0.1051, +0.3947],  # 34
    [+0.2002, +0.3596],  # 35
    [-0.5640, -0.2140],  # 36
    [-0.4652, -0.2645],  # 37
    [-0.3523, -0.2666],  # 38
    [-0.2525, -0.2070],  # 39
    [-0.3574, -0.1844],  # 40
    [-0.4687, -0.1835],  # 41
    [+0.2525, -0.2070],  # 42
    [+0.3523, -0.2666],  # 43
    [+0.4652, -0.2645],  # 44
    [+0.5640, -0.2140],  # 45
    [+0.4687, -0.1835],  # 46
    [+0.3574, -0.1844],  # 47
    [-0.3575, +0.7482],  # 48
    [-0.2310, +0.6774],  # 49
    [-0.1033, +0.6465],  # 50
    [+0.0000, +0.6706],  # 51
    [+0.1033, +0.6465],  # 52
    [+0.2310, +0.6774],  # 53
    [+0.3575, +0.7482],  # 54
    [+0.2361, +0.8551],  # 55
    [+0.1110, +0.9066],  # 56
    [+0.0000, +0.9166],  # 57
    [-0.1110, +0.9066],  # 58
    [-0.2361, +0.8551],  # 59
    [-0.2986, +0.7462],  # 60
    [-0.1043, +0.7145],  # 61
    [+0.0000, +0.7249],  # 62
    [+0.1043, +0.7145],  # 63
    [+0.2986, +0.7462],  # 64
    [+0.1058, +0.7838],  # 65
    [+0.0000, +0.7973],  # 66
    [-0.1058, +0.7838],  # 67
])
_LM68.setflags(write=False)

# Face oval fitted to the jaw points of _LM68 (module docstring), enlarged by 3 %.
OVAL_CENTER_Y = -0.03
FW0 = 1.025  # horizontal semi-axis
FH0 = 1.515  # vertical semi-axis below the widest line
OVAL_TOP = -1.36  # Y of the top of the oval (canonical y = 3.2)
EYE_DX0 = 0.41
NOSE_W0 = 0.10

# Per-parameter spread multipliers of FaceIdentity.random (relative to `spread`). Geometry
# moves less than amplitudes so that every random face keeps a plausible layout and fits the frame.
_SPREAD = {"a_n": 1.0, "w_n": 0.5, "a_e": 1.0, "a_b": 1.0, "a_c": 1.0, "a_l": 1.0, "a_ch": 1.0,
           "fw": 0.2, "fh": 0.15, "eye_dx": 0.2, "eye_h": 0.6, "mouth_w": 0.3}


@dataclass(frozen=True)
class FaceIdentity:
    """Shape and colour parameters of the analytic face (ALGORITHMS §3.2); defaults = the generic template.

    Amplitudes ``a_*`` are in canonical px (height towards the camera), positions and widths in
    normalised units (80 canonical px). ``eye_h`` and ``mouth_w`` scale the eye opening and the
    mouth width of the landmark layout. Colours are linear RGB albedo in [0, 1].
    """

    a_n: float = 28.0  # nose height
    w_n: float = NOSE_W0  # nose width
    a_e: float = 12.0  # eye socket depth
    a_b: float = 6.0  # brow ridge
    a_c: float = 6.0  # cheeks
    a_l: float = 6.0  # lips
    a_ch: float = 8.0  # chin
    fw: float = FW0  # face oval half width
    fh: float = FH0  # face oval half height (below the widest line)
    eye_dx: float = EYE_DX0  # half the inter-ocular distance
    eye_h: float = 1.0  # eye opening, relative to the template
    mouth_w: float = 1.0  # mouth width, relative to the template
    skin: tuple[float, float, float] = (0.78, 0.58, 0.47)
    lips: tuple[float, float, float] = (0.62, 0.30, 0.30)
    brows: tuple[float, float, float] = (0.16, 0.11, 0.08)
    iris: tuple[float, float, float] = (0.25, 0.16, 0.10)
    hair: tuple[float, float, float] = (0.10, 0.07, 0.05)
    hairline: float = -0.98  # Y of the hairline at the forehead centre; <= OVAL_TOP for no hair
    texture_seed: int = 0  # seed of the skin noise texture

    def __post_init__(self):
        # The oval must fit the 194 x 244 frame.
        if not (0.5 < self.fw <= (CENTER_X - 2) / UNIT):
            raise ValueError(f"fw={self.fw} out of range (0.5, {(CENTER_X - 2) / UNIT:.3f}]")
        bottom = OVAL_CENTER_Y + self.fh
        if not (0.8 < self.fh and bottom <= (CANONICAL_HEIGHT - 3 - CENTER_Y) / UNIT):
            raise ValueError(f"fh={self.fh} puts the chin outside the frame")

    @classmethod
    def random(cls, rng: np.random.Generator, spread: float = 0.3) -> "FaceIdentity":
        """A random identity: each shape parameter uniform within +-spread (scaled per parameter) of the default."""
        base = cls()
        kw = {k: getattr(base, k) * (1 + m * spread * rng.uniform(-1, 1)) for k, m in _SPREAD.items()}
        tone = rng.uniform(0.45, 1.0)  # darker .. lighter skin
        warm = rng.uniform(-0.04, 0.04)
        kw["skin"] = tuple(float(np.clip(c * tone + w, 0.05, 0.95))
                           for c, w in zip((0.85, 0.64, 0.52), (warm, 0.0, -warm)))
        kw["lips"] = tuple(float(c * tone * rng.uniform(0.9, 1.1)) for c in (0.70, 0.34, 0.33))
        kw["brows"] = tuple(float(c * rng.uniform(0.5, 2.0)) for c in (0.14, 0.10, 0.07))
        kw["iris"] = tuple(float(c) for c in rng.uniform([0.08, 0.06, 0.04], [0.35, 0.30, 0.30]))
        kw["hair"] = tuple(float(c) for c in np.array([0.12, 0.08, 0.05]) * rng.choice([0.5, 1.0, 2.0, 4.0]))
        kw["hairline"] = float(rng.uniform(-1.10, -0.90))
        kw["texture_seed"] = int(rng.integers(0, 2**31 - 1))
        return cls(**kw)


def face_landmarks_normalised(identity: FaceIdentity) -> np.ndarray:
    """(68, 2) landmark positions (X, Y) of an identity, in normalised units."""
    lm = _LM68.copy()
    side = np.sign(lm[:, 0])
    # jaw: follows the oval
    jaw = slice(0, 17)
    lm[jaw, 0] *= identity.fw / FW0
    below = lm[jaw, 1] > OVAL_CENTER_Y
    lm[jaw, 1] = np.where(below, OVAL_CENTER_Y + (lm[jaw, 1] - OVAL_CENTER_Y) * identity.fh / FH0, lm[jaw, 1])
    # brows and eyes follow the eye spacing; the eye opening scales about the eye centre line
    for sl in (slice(17, 27), slice(36, 48)):
        lm[sl, 0] += side[sl] * (identity.eye_dx - EYE_DX0)
    lm[36:48, 1] = -0.22 + (lm[36:48, 1] + 0.22) * identity.eye_h
    lm[31:36, 0] *= identity.w_n / NOSE_W0
    lm[48:68, 0] *= identity.mouth_w
    return lm


def _gauss(X, Y, x0, y0, sx, sy):
    return np.exp(-0.5 * ((X - x0) / sx) ** 2 - 0.5 * ((Y - y0) / sy) ** 2)


@dataclass(frozen=True)
class _Layout:
    """Centres of the surface features, taken from an identity's landmark layout."""

    lm: np.ndarray
    eye: np.ndarray = field(init=False)  # (2,) |X|, Y of the eye centres
    brow: np.ndarray = field(init=False)
    nose_tip_y: float = field(init=False)
    ala: np.ndarray = field(init=False)
    upper_lip_y: float = field(init=False)
    lower_lip_y: float = field(init=False)
    chin_y: float = field(init=False)

    def __post_init__(self):
        lm = self.lm
        set_ = functools.partial(object.__setattr__, self)
        set_("eye", np.array([lm[42:48, 0].mean(), lm[36:48, 1].mean()]))
        set_("brow", np.array([lm[22:27, 0].mean(), lm[17:27, 1].mean() + 0.03]))
        set_("nose_tip_y", float(lm[30, 1]))
        set_("ala", np.array([0.85 * lm[35, 0], lm[35, 1] - 0.02]))
        set_("upper_lip_y", float((lm[51, 1] + lm[62, 1]) / 2))
        set_("lower_lip_y", float((lm[57, 1] + lm[66, 1]) / 2))
        set_("chin_y", float(lm[8, 1] - 0.25))


def _layout(identity: FaceIdentity) -> _Layout:
    return _Layout(face_landmarks_normalised(identity))


def face_height(identity: FaceIdentity, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Height h(X, Y) towards the camera, in canonical px, at normalised points (any shape)."""
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    L = _layout(identity)
    i = identity
    sx_head = 1.3 * i.fw / FW0
    h = 60.0 * np.sqrt(np.maximum(0.0, 1 - (X / sx_head) ** 2 - ((Y - OVAL_CENTER_Y) / 1.8) ** 2))
    h = h + 0.55 * i.a_n * _gauss(X, Y, 0.0, L.nose_tip_y - 0.25, i.w_n, 0.25)
    h = h + i.a_n * _gauss(X, Y, 0.0, L.nose_tip_y + 0.015, 1.2 * i.w_n, 0.10)
    mw = i.mouth_w
    for s in (-1.0, 1.0):
        h = h + 0.3 * i.a_n * _gauss(X, Y, s * L.ala[0], L.ala[1], 0.07, 0.06)
        h = h - i.a_e * _gauss(X, Y, s * L.eye[0], L.eye[1], 0.17, 0.11)
        h = h + i.a_b * _gauss(X, Y, s * L.brow[0], L.brow[1], 0.22, 0.07)
        h = h + i.a_c * _gauss(X, Y, s * 0.52 * i.fw / FW0, 0.15, 0.18, 0.18)
    h = h + i.a_l * (_gauss(X, Y, 0.0, L.upper_lip_y, 0.22 * mw, 0.05) + _gauss(X, Y, 0.0, L.lower_lip_y, 0.20 * mw, 0.06))
    h = h + i.a_ch * _gauss(X, Y, 0.0, L.chin_y, 0.28, 0.14)
    return h


def face_oval(identity: FaceIdentity, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Normalised oval radius (<= 1 inside the face) at normalised points."""
    dy = Y - OVAL_CENTER_Y
    sy = np.where(dy > 0, identity.fh, OVAL_CENTER_Y - OVAL_TOP)
    return np.sqrt((X / identity.fw) ** 2 + (dy / sy) ** 2)


def _grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray, float]:
    scale = width / CANONICAL_WIDTH
    if abs(height / CANONICAL_HEIGHT - scale) > 1.0 / CANONICAL_HEIGHT:
        raise ValueError(f"grid {height}x{width} is not proportional to {CANONICAL_HEIGHT}x{CANONICAL_WIDTH}")
    x = np.arange(width) / scale
    y = np.arange(height) / scale
    X, Y = np.meshgrid((x - CENTER_X) / UNIT, (y - CENTER_Y) / UNIT)
    return X, Y, scale


def face_depth(identity: FaceIdentity, height: int = CANONICAL_HEIGHT,
               width: int = CANONICAL_WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """Depth map Z (height, width) float64 and face mask (bool) of an identity, neutral expression.

    A grid other than 244 x 194 must be proportional to it: it samples the same face at the
    canonical points ``(j, i) / s`` with ``s = width/194``, and returns depths in its own px (``Z * s``).
    The depth is finite everywhere, including outside the mask.
    """
    X, Y, scale = _grid(height, width)
    depth = (BASE_DEPTH - face_height(identity, X, Y)) * scale
    mask = face_oval(identity, X, Y) <= 1.0
    return depth, mask


def face_normals(identity: FaceIdentity, height: int = CANONICAL_HEIGHT,
                 width: int = CANONICAL_WIDTH) -> np.ndarray:
    """Unit normals (height, width, 3) ``(Z_x, Z_y, -1)/|.|`` of the analytic depth (central differences, 1e-3 px)."""
    X, Y, _ = _grid(height, width)
    e = 1e-3 / UNIT  # the gradient is scale-free: dZ/dx in px/px
    zx = -(face_height(identity, X + e, Y) - face_height(identity, X - e, Y)) / (2e-3)
    zy = -(face_height(identity, X, Y + e) - face_height(identity, X, Y - e)) / (2e-3)
    n = np.stack([zx, zy, -np.ones_like(zx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def face_landmarks3d(identity: FaceIdentity) -> np.ndarray:
    """(68, 3) landmarks (x, y, Z) in canonical px, iBUG order, on the analytic surface."""
    lm = face_landmarks_normalised(identity)
    X, Y = lm[:, 0], lm[:, 1]
    return np.stack([X * UNIT + CENTER_X, Y * UNIT + CENTER_Y, BASE_DEPTH - face_height(identity, X, Y)], axis=1)


@dataclass(frozen=True)
class FaceTemplate:
    """A face in the canonical frame (244 x 194): depth, mask, normals and 68 3D landmarks."""

    depth: np.ndarray  # (244, 194) float64, Z in canonical px
    mask: np.ndarray  # (244, 194) bool, the face oval
    normals: np.ndarray  # (244, 194, 3) float64 unit, (Z_x, Z_y, -1)/|.|
    landmarks3d: np.ndarray  # (68, 3) float64 (x, y, Z), iBUG order

    @property
    def fiducials3d(self) -> np.ndarray:
        """(49, 3) the paper's 49 fiducials, ``landmarks3d[IDX49]``."""
        return self.landmarks3d[list(IDX49)]

    @classmethod
    def from_identity(cls, identity: FaceIdentity) -> "FaceTemplate":
        depth, mask = face_depth(identity)
        arrays = dict(depth=depth, mask=mask, normals=face_normals(identity),
                      landmarks3d=face_landmarks3d(identity))
        for a in arrays.values():
            a.setflags(write=False)
        return cls(**arrays)


@functools.lru_cache(maxsize=1)
def generic_template() -> FaceTemplate:
    """The generic template: default identity, neutral expression (cached, arrays read-only)."""
    return FaceTemplate.from_identity(FaceIdentity())
