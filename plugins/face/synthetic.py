"""Synthetic faces with known ground truth (ALGORITHMS §3.2, §3.3).

A face is the analytic surface of :mod:`persona.plugins.face.template` for an identity. It is held
as a mesh *parametrised on the canonical grid*: the vertex at canonical pixel ``(u, v)`` lies at
``verts[v, u] = (u + 80 dX, v + 80 dY, Z(u, v) - dh)``, where ``(dX, dY, dh)`` is the smooth
displacement field of the expression (normalised units for dX and dY, canonical px for dh). The
albedo is painted on the parametrisation, so it moves with the skin. The landmarks move by the
same field, evaluated at their own parameters.

Shading is first-order spherical harmonics, ``I = albedo * max(0, l0 + l.n)``. The light
``(l0, l)`` is given in the face's frontal frame, and a posed render rotates it with the head
(``l_cam = R l``). The shading of a skin point therefore does not depend on the pose.

Rendering ray-casts the mesh with ``open3d.t.geometry.RaycastingScene``. Perspective rays are
built as ``K^-1 [j, i, 1]`` from the camera centre: open3d's ``create_rays_pinhole`` would add
half a pixel (ALGORITHMS §0). Vertex albedo and normals are interpolated with the hit's
barycentric weights.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d
from scipy.ndimage import gaussian_filter

from .template import (
    BASE_DEPTH,
    CANONICAL_HEIGHT,
    CANONICAL_WIDTH,
    CENTER_X,
    CENTER_Y,
    FW0,
    IDX49,
    UNIT,
    FaceIdentity,
    face_height,
    face_landmarks_normalised,
    face_oval,
)

__all__ = [
    "Expression", "Light", "SyntheticFace", "SyntheticPhoto", "expression_field", "make_face",
    "render_photo", "render_canonical", "look_at_pose", "make_collection", "make_driver_video",
    "random_expression", "random_background",
]

H, W = CANONICAL_HEIGHT, CANONICAL_WIDTH
_PIVOT = np.array([CENTER_X, CENTER_Y, 230.0])  # rotation centre of the head, behind the face
_FACE_WIDTH = 2 * FW0 * UNIT  # canonical width of the generic face oval
_JAW_Z = 165.0  # typical depth of the face outline, where `face_px` is measured


# ----------------------------------------------------------------------------- parameters

@dataclass(frozen=True)
class Expression:
    """Expression weights, about [-1, 1] (blink in [0, 1]).

    smile > 0 moves the mouth corners out and up and raises the cheeks (< 0 frowns). open > 0
    drops the jaw, and open = -1 closes the identity's resting lip gap exactly. brow > 0 raises
    the brows. blink = 1 closes the identity's own eye opening exactly.
    """

    smile: float = 0.0
    open: float = 0.0
    brow: float = 0.0
    blink: float = 0.0

    def __post_init__(self):
        if not 0.0 <= self.blink <= 1.0:
            raise ValueError(f"blink={self.blink} must lie in [0, 1]")
        if self.open < -1.0:
            raise ValueError(f"open={self.open} must be >= -1 (-1 closes the lips)")

    def as_array(self) -> np.ndarray:
        return np.array([self.smile, self.open, self.brow, self.blink])


@dataclass(frozen=True)
class Light:
    """First-order SH light: ``I = albedo * max(0, ambient + direction . n)``.

    The direction is in the face's frontal frame (x right, y down, z away from the viewer). It has
    z < 0 for a light on the camera side, and a posed render rotates it with the head.
    """

    ambient: float = 0.45
    direction: tuple[float, float, float] = (0.2, -0.25, -0.65)

    @classmethod
    def random(cls, rng: np.random.Generator, *, ambient=(0.3, 0.6), strength=(0.5, 0.9),
               max_angle_deg: float = 60.0) -> "Light":
        """l0 ~ U(ambient), |l| ~ U(strength), direction uniform on the cap within max_angle of -z."""
        cos_max = np.cos(np.radians(max_angle_deg))
        cz = rng.uniform(cos_max, 1.0)
        phi = rng.uniform(0, 2 * np.pi)
        s = np.sqrt(1 - cz**2)
        d = np.array([s * np.cos(phi), s * np.sin(phi), -cz]) * rng.uniform(*strength)
        return cls(float(rng.uniform(*ambient)), tuple(float(v) for v in d))

    def shade(self, normals: np.ndarray) -> np.ndarray:
        """``max(0, l0 + l.n)`` for normals (..., 3) in the same frame as the light."""
        return np.maximum(0.0, self.ambient + normals @ np.asarray(self.direction))

    def rotated(self, R: np.ndarray) -> "Light":
        return Light(self.ambient, tuple(float(v) for v in R @ np.asarray(self.direction)))


# ----------------------------------------------------------------------------- expression field

def _slit(X, Y, upper_pts, lower_pts):
    """Upper and lower lid curves (piecewise linear in X through landmarks) and the opening."""
    up = np.interp(X, upper_pts[:, 0], upper_pts[:, 1])
    lo = np.interp(X, lower_pts[:, 0], lower_pts[:, 1])
    return up, lo, np.maximum(lo - up, 0.0)


def _taper(d, width):
    """1 at d <= 0, smooth cosine fall to 0 at d >= width."""
    t = np.clip(d / width, 0.0, 1.0)
    return 0.5 * (1 + np.cos(np.pi * t))


def _g(X, Y, x0, y0, sx, sy):
    return np.exp(-0.5 * ((X - x0) / sx) ** 2 - 0.5 * ((Y - y0) / sy) ** 2)


def expression_field(identity: FaceIdentity, expression: Expression, X, Y):
    """Displacement ``(dX, dY, dh)`` of the parametrisation at normalised points (X, Y).

    dX, dY are in normalised units (x 80 = canonical px), dh in canonical px towards the camera.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    lm = face_landmarks_normalised(identity)
    e = expression
    dX = np.zeros(np.broadcast_shapes(X.shape, Y.shape))
    dY = np.zeros_like(dX)
    dh = np.zeros_like(dX)
    mw = identity.mouth_w
    if e.smile:
        for corner, side in ((lm[48], -1.0), (lm[54], 1.0)):
            g = _g(X, Y, corner[0], corner[1], 0.20 * mw, 0.16)
            dX += e.smile * 0.05 * side * g
            dY -= e.smile * 0.045 * g
            dh += e.smile * 4.0 * _g(X, Y, side * 0.42 * identity.fw / FW0, 0.42, 0.15, 0.15)
    if e.open > 0:
        up, lo, gap = _slit(X, Y, lm[[60, 61, 62, 63, 64]], lm[[60, 67, 66, 65, 64]])
        ramp = np.clip((Y - up) / np.maximum(gap, 0.05), 0.0, 1.0)
        ramp = ramp * ramp * (3 - 2 * ramp)
        dY += e.open * 0.15 * ramp * np.exp(-0.5 * (X / (0.45 * mw)) ** 2)
        dh -= e.open * 3.0 * ramp * _g(X, Y, 0.0, lm[8, 1] - 0.3, 0.4, 0.35)
    elif e.open < 0:
        # Close the resting lip gap: points between the inner lips collapse onto the upper one.
        up, lo, gap = _slit(X, Y, lm[[60, 61, 62, 63, 64]], lm[[60, 67, 66, 65, 64]])
        dY += e.open * np.clip(Y - up, 0.0, gap) * _taper(Y - lo, 0.5)
    if e.brow:
        for sl in (slice(17, 22), slice(22, 27)):
            c = lm[sl].mean(axis=0)
            dY -= e.brow * 0.07 * _g(X, Y, c[0], c[1], 0.30, 0.14)
    if e.blink:
        for upper, lower in (([36, 37, 38, 39], [36, 41, 40, 39]), ([42, 43, 44, 45], [42, 47, 46, 45])):
            up, lo, opening = _slit(X, Y, lm[upper], lm[lower])
            # between the lids: slide to the lower lid (monotone for blink <= 1, no fold);
            # above: the lid skin follows and the pull fades out towards the brow
            dY += e.blink * np.minimum(np.maximum(lo - Y, 0.0), opening) * _taper(up - Y, 0.2)
    return dX, dY, dh


# ----------------------------------------------------------------------------- albedo

def _ss_pts(pts_norm: np.ndarray, ss: int) -> np.ndarray:
    """Normalised points -> fixed-point (shift 4) coordinates on an ss-times supersampled canonical grid."""
    x = pts_norm[:, 0] * UNIT + CENTER_X
    y = pts_norm[:, 1] * UNIT + CENTER_Y
    xs = (x + 0.5) * ss - 0.5
    ys = (y + 0.5) * ss - 0.5
    return np.round(np.stack([xs, ys], axis=1) * 16).astype(np.int32)


def _paint(layer_fn, ss=4, blur=0.0) -> np.ndarray:
    """Anti-aliased coverage (H, W) in [0, 1] of shapes drawn by layer_fn(canvas, ss) at ss x resolution."""
    canvas = np.zeros((H * ss, W * ss), np.float32)
    layer_fn(canvas, ss)
    cov = cv2.resize(canvas, (W, H), interpolation=cv2.INTER_AREA).astype(np.float64)
    if blur:
        cov = gaussian_filter(cov, blur)
    return np.clip(cov, 0.0, 1.0)


def _blend(img, cov, colour):
    return img * (1 - cov[..., None]) + np.asarray(colour)[None, None, :] * cov[..., None]


@functools.lru_cache(maxsize=32)
def _albedo(identity: FaceIdentity) -> np.ndarray:
    """Albedo (244, 194, 3) on the parametrisation: textured skin, brows, eyes, lips, nostrils."""
    lm = face_landmarks_normalised(identity)
    rng = np.random.default_rng(identity.texture_seed)
    skin = np.asarray(identity.skin)
    tex = np.zeros((H, W))
    for sigma, amp in ((1.0, 0.035), (3.0, 0.035), (8.0, 0.04)):
        n = gaussian_filter(rng.standard_normal((H, W)), sigma)
        tex += amp * n / n.std()
    chroma = gaussian_filter(rng.standard_normal((H, W, 3)), (4.0, 4.0, 0))
    chroma = 0.015 * chroma / chroma.std()
    img = skin[None, None, :] * (1 + tex[..., None] + chroma)
    # slightly darker, warmer rim of the face (shadowed temples and jaw read better in HOG)
    X, Y = np.meshgrid((np.arange(W) - CENTER_X) / UNIT, (np.arange(H) - CENTER_Y) / UNIT)
    r = face_oval(identity, X, Y)
    img *= (1 - 0.12 * np.clip((r - 0.75) / 0.25, 0, 1) ** 2)[..., None]

    def polyline(idx, closed=False, thickness=1.0):
        def fn(c, ss):
            cv2.polylines(c, [_ss_pts(lm[idx], ss)], closed, 1.0, max(1, int(round(thickness * ss))),
                          cv2.LINE_AA, shift=4)
        return fn

    def poly(idx):
        def fn(c, ss):
            cv2.fillPoly(c, [_ss_pts(lm[idx], ss)], 1.0, cv2.LINE_AA, shift=4)
        return fn

    def ellipse(centre, axes):
        def fn(c, ss):
            p = _ss_pts(np.asarray(centre)[None], ss)[0]
            ax = tuple(int(round(a * UNIT * ss * 16)) for a in axes)
            cv2.ellipse(c, (int(p[0]), int(p[1])), ax, 0, 0, 360, 1.0, -1, cv2.LINE_AA, shift=4)
        return fn

    # hair above a hairline that curves down to the temples (a strong HOG cue for the detector)
    hairline = identity.hairline + 0.38 * (X / identity.fw) ** 2
    hair = np.clip((hairline - Y) * UNIT / 3.0 + 0.5, 0.0, 1.0) * (r <= 1.0 + 2.0 / UNIT)
    hair_tex = np.asarray(identity.hair)[None, None, :] * (1 + 2.0 * tex[..., None])
    img = img * (1 - hair[..., None]) + hair_tex * hair[..., None]
    brows = np.asarray(identity.brows)
    for idx in ([17, 18, 19, 20, 21], [22, 23, 24, 25, 26]):
        # the brow hair sits on and just below dlib's brow points
        pts = lm[idx] + np.array([0.0, 0.025])
        lm_b = lm.copy()
        lm_b[idx] = pts
        cov = _paint(lambda c, ss, idx=idx, lm_b=lm_b: cv2.polylines(
            c, [_ss_pts(lm_b[idx], ss)], False, 1.0, int(round(5.0 * ss)), cv2.LINE_AA, shift=4), blur=0.8)
        img = _blend(img, 0.85 * cov, brows)
    for eye, upper in ((list(range(36, 42)), [36, 37, 38, 39]), (list(range(42, 48)), [42, 43, 44, 45])):
        sclera = _paint(poly(eye))
        centre = lm[eye].mean(axis=0)
        radius = 0.058 * max(identity.eye_h, 0.6)
        iris = _paint(ellipse(centre, (radius, radius))) * sclera
        pupil = _paint(ellipse(centre, (0.4 * radius, 0.4 * radius))) * sclera
        img = _blend(img, sclera, (0.80, 0.78, 0.74))
        img = _blend(img, iris, identity.iris)
        img = _blend(img, pupil, (0.03, 0.03, 0.03))
        lash = _paint(polyline(upper, thickness=1.6), blur=0.4)
        img = _blend(img, 0.85 * lash, (0.05, 0.04, 0.04))
        lid = _paint(polyline(eye, closed=True, thickness=1.0), blur=0.5)
        img = _blend(img, 0.35 * lid, skin * 0.45)
    lips = _paint(poly(list(range(48, 60))), blur=0.6)
    img = _blend(img, 0.9 * lips, identity.lips)
    mouth = _paint(poly(list(range(60, 68))), blur=0.4)
    img = _blend(img, mouth, (0.10, 0.04, 0.04))
    line = _paint(polyline([60, 61, 62, 63, 64], thickness=1.5), blur=0.5)
    img = _blend(img, 0.8 * line, (0.12, 0.05, 0.05))
    for a, b in ((31, 32), (35, 34)):
        c = 0.55 * lm[a] + 0.45 * lm[b] - np.array([0.0, 0.025])
        nostril = _paint(ellipse(c, (0.045 * identity.w_n / 0.1, 0.022)), blur=0.8)
        img = _blend(img, 0.85 * nostril, skin * 0.25)
    out = np.clip(img, 0.0, 1.0)
    out.setflags(write=False)
    return out


# ----------------------------------------------------------------------------- face

@dataclass
class SyntheticFace:
    """Ground truth of one identity and expression in the canonical frame (244 x 194).

    ``depth``, ``mask``, ``normals`` and ``albedo`` describe what a frontal orthographic camera sees
    on the canonical grid. For the neutral expression they are the analytic template arrays.
    ``verts`` is the deformed parametrisation: it maps each neutral canonical pixel ``(u, v)`` to
    its (x, y, Z) under the expression, the GT correspondence of §3.2. ``vert_mask``,
    ``vert_normals`` and ``vert_albedo`` live on the same parameter grid.
    """

    identity: FaceIdentity
    expression: Expression
    depth: np.ndarray  # (244, 194) float64, frontal view; BASE_DEPTH-scale finite values off the face
    mask: np.ndarray  # (244, 194) bool, frontal view
    normals: np.ndarray  # (244, 194, 3) unit, frontal view
    albedo: np.ndarray  # (244, 194, 3) [0, 1], frontal view
    landmarks3d: np.ndarray  # (68, 3) (x, y, Z) canonical px under the expression
    verts: np.ndarray  # (244, 194, 3) deformed parametrisation
    vert_mask: np.ndarray  # (244, 194) bool, parameters on the face (the neutral oval)
    vert_normals: np.ndarray  # (244, 194, 3) unit normals of the deformed surface at each parameter
    vert_albedo: np.ndarray  # (244, 194, 3) albedo painted on the parametrisation
    triangles: np.ndarray = field(repr=False)  # (m, 3) int, indices into the flattened (244*194) grid

    @property
    def fiducials3d(self) -> np.ndarray:
        return self.landmarks3d[list(IDX49)]


def _deformed(identity, expression, X, Y):
    """Deformed positions (x, y, Z) in canonical px of parameters (X, Y) (normalised)."""
    dX, dY, dh = expression_field(identity, expression, X, Y)
    return np.stack([(X + dX) * UNIT + CENTER_X, (Y + dY) * UNIT + CENTER_Y,
                     BASE_DEPTH - face_height(identity, X, Y) - dh], axis=-1)


@functools.lru_cache(maxsize=8)
def _grid_topology(identity: FaceIdentity):
    X, Y = np.meshgrid((np.arange(W) - CENTER_X) / UNIT, (np.arange(H) - CENTER_Y) / UNIT)
    mask = face_oval(identity, X, Y) <= 1.0
    idx = np.arange(H * W).reshape(H, W)
    quad = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, :-1] & mask[1:, 1:]
    a, b, c, d = idx[:-1, :-1][quad], idx[:-1, 1:][quad], idx[1:, :-1][quad], idx[1:, 1:][quad]
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    for arr in (X, Y, mask, tris):
        arr.setflags(write=False)
    return X, Y, mask, tris


def make_face(identity: FaceIdentity | None = None, expression: Expression = Expression()) -> SyntheticFace:
    """The ground-truth face of an identity (default: the generic template) under an expression."""
    identity = FaceIdentity() if identity is None else identity
    X, Y, vmask, tris = _grid_topology(identity)
    verts = _deformed(identity, expression, X, Y)
    e = 1e-3 / UNIT
    mu = (_deformed(identity, expression, X + e, Y) - _deformed(identity, expression, X - e, Y)) / 2e-3
    mv = (_deformed(identity, expression, X, Y + e) - _deformed(identity, expression, X, Y - e)) / 2e-3
    n = -np.cross(mu, mv)
    vnormals = n / np.linalg.norm(n, axis=-1, keepdims=True)
    valbedo = _albedo(identity)
    lm = face_landmarks_normalised(identity)
    lm3 = _deformed(identity, expression, lm[:, 0], lm[:, 1])
    neutral = not expression.as_array().any()
    if neutral:
        depth = verts[..., 2].copy()
        mask, normals, albedo = vmask.copy(), vnormals.copy(), np.array(valbedo)
    else:
        face = SyntheticFace(identity, expression, None, None, None, None, lm3, verts, vmask, vnormals,
                             np.asarray(valbedo), tris)
        r = render_canonical(face)
        depth = np.where(r["mask"], r["depth"], BASE_DEPTH - face_height(identity, X, Y))
        mask, normals, albedo = r["mask"], r["normals"], r["albedo"]
        normals[~mask] = vnormals[~mask]
    return SyntheticFace(identity, expression, depth, mask, normals, albedo, lm3, verts, vmask.copy(),
                         vnormals, np.array(valbedo), tris)


# ----------------------------------------------------------------------------- ray casting

class _Scene:
    """A ray-casting scene of one triangle mesh."""

    def __init__(self, verts: np.ndarray, tris: np.ndarray):
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(verts, dtype=np.float32)),
                                 o3d.core.Tensor(np.ascontiguousarray(tris, dtype=np.uint32)))

    def cast(self, origins: np.ndarray, dirs: np.ndarray):
        """t_hit (inf on a miss, in units of |dir|), primitive ids and barycentric uvs of each ray."""
        rays = np.concatenate([origins, dirs], axis=-1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        return ans["t_hit"].numpy(), ans["primitive_ids"].numpy(), ans["primitive_uvs"].numpy()


def _cast(verts: np.ndarray, tris: np.ndarray, origins: np.ndarray, dirs: np.ndarray):
    return _Scene(verts, tris).cast(origins, dirs)


def _interp(attr: np.ndarray, tris: np.ndarray, prim: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """Barycentric interpolation of per-vertex attr (n, k) at hits (prim, uv): w = (1-u-v, u, v)."""
    t = tris[prim]
    u, v = uvs[:, :1].astype(np.float64), uvs[:, 1:2].astype(np.float64)
    return attr[t[:, 0]] * (1 - u - v) + attr[t[:, 1]] * u + attr[t[:, 2]] * v


def render_canonical(face: SyntheticFace) -> dict[str, np.ndarray]:
    """Orthographic frontal ray-cast of the (deformed) mesh on the canonical grid.

    Rays ``origin = (j, i, z0)``, direction ``(0, 0, 1)``. Returns depth (inf off the face), mask,
    normals and albedo interpolated from the vertices, and the hit parameters ``uv`` (NaN off the face).
    """
    v = face.verts.reshape(-1, 3)
    z0 = float(v[face.vert_mask.ravel(), 2].min()) - 10.0
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    origins = np.stack([jj.ravel(), ii.ravel(), np.full(H * W, z0)], axis=1)
    dirs = np.tile([0.0, 0.0, 1.0], (H * W, 1))
    # cast relative to a local origin: keeps float32 rounding well below 1e-3 px
    off = np.array([CENTER_X, CENTER_Y, z0])
    t, prim, uvs = _cast(v - off, face.triangles, origins - off, dirs)
    hit = np.isfinite(t)
    depth = np.full(H * W, np.inf)
    depth[hit] = z0 + t[hit].astype(np.float64)
    return _gather(face, hit, prim, uvs, depth, (H, W))


def _gather(face, hit, prim, uvs, depth, shape):
    h, w = shape
    normals = np.zeros((h * w, 3))
    albedo = np.zeros((h * w, 3))
    uv = np.full((h * w, 2), np.nan)
    if hit.any():
        p, q = prim[hit], uvs[hit]
        n = _interp(face.vert_normals.reshape(-1, 3), face.triangles, p, q)
        normals[hit] = n / np.linalg.norm(n, axis=1, keepdims=True)
        albedo[hit] = _interp(face.vert_albedo.reshape(-1, 3), face.triangles, p, q)
        jj, ii = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        uv[hit] = _interp(np.stack([jj.ravel(), ii.ravel()], 1), face.triangles, p, q)
    return dict(depth=depth.reshape(h, w), mask=hit.reshape(h, w), normals=normals.reshape(h, w, 3),
                albedo=albedo.reshape(h, w, 3), uv=uv.reshape(h, w, 2))


# ----------------------------------------------------------------------------- photos

@dataclass
class SyntheticPhoto:
    """A rendered photo with its ground truth.

    ``rvec, tvec`` map canonical points (x, y, Z) to the camera frame (OpenCV), so
    ``cv2.projectPoints(face.landmarks3d, rvec, tvec, camera, None)`` gives ``landmarks``.
    ``uv`` (h, w, 2) holds the canonical parameter (u, v) seen at each pixel: the GT map from the
    photo to the neutral canonical grid, NaN off the face. ``depth`` is the camera z of the
    surface (inf off the face).
    """

    image: np.ndarray  # (h, w, 3) uint8 RGB
    landmarks: np.ndarray  # (68, 2) float64 image (x, y)
    visible: np.ndarray  # (68,) bool
    rvec: np.ndarray  # (3,)
    tvec: np.ndarray  # (3,)
    camera: np.ndarray  # (3, 3) K
    light: Light  # in the face frame; light.rotated(R) in the camera frame
    expression: Expression
    identity: FaceIdentity
    face_mask: np.ndarray = field(repr=False)  # (h, w) bool
    depth: np.ndarray = field(repr=False)  # (h, w) float64 camera z, inf off the face
    uv: np.ndarray = field(repr=False)  # (h, w, 2) float32 canonical parameters, NaN off the face

    @property
    def fiducials(self) -> np.ndarray:
        return self.landmarks[list(IDX49)]


def random_background(rng: np.random.Generator, image_size: tuple[int, int]) -> np.ndarray:
    """A plausible backdrop (h, w, 3) float in [0, 1]: a neutral tint, a soft gradient, some blotches."""
    h, w = image_size
    base = rng.choice([rng.uniform(0.05, 0.3), rng.uniform(0.55, 0.9)])
    tint = base * (1 + rng.uniform(-0.25, 0.25, 3))
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    grad = rng.uniform(-0.15, 0.15, 2)
    img = tint[None, None, :] + (grad[0] * (xx - 0.5) + grad[1] * (yy - 0.5))[..., None]
    small = rng.standard_normal((16, 16, 3))
    small[..., 1:] = small[..., :1] + 0.3 * small[..., 1:]  # mostly luminance, a little colour
    blot = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    img += 0.06 * blot / (blot.std() + 1e-12)
    return np.clip(img, 0.0, 1.0)


def render_photo(face: SyntheticFace, *, rvec, tvec, camera, light: Light = Light(),
                 image_size: tuple[int, int] = (250, 250), background=None, noise_sigma: float = 0.0,
                 rng: np.random.Generator | None = None, supersample: int = 1) -> SyntheticPhoto:
    """Perspective render of a face at pose (rvec, tvec) with intrinsics ``camera``.

    background: None (mid grey), an RGB triple, or an (h, w, 3) float image in [0, 1].
    noise_sigma: std of additive Gaussian pixel noise (intensity units, [0, 1]), needs ``rng``.
    supersample: s x s rays per pixel at offsets symmetric about the pixel centre (anti-aliasing);
    the GT maps ``face_mask``, ``depth`` and ``uv`` always come from the ray through the pixel centre.
    """
    h, w = image_size
    K = np.asarray(camera, dtype=np.float64)
    rvec = np.asarray(rvec, dtype=np.float64).reshape(3)
    tvec = np.asarray(tvec, dtype=np.float64).reshape(3)
    R = cv2.Rodrigues(rvec)[0]
    vcam = face.verts.reshape(-1, 3) @ R.T + tvec
    used = np.zeros(len(vcam), bool)
    used[face.triangles.ravel()] = True
    if np.any(vcam[used, 2] <= 0):
        raise ValueError("the face is not entirely in front of the camera (z <= 0)")
    scene = _Scene(vcam, face.triangles)

    # only cast rays inside the projected bounding box of the mesh
    proj = vcam[used] @ K.T
    proj = proj[:, :2] / proj[:, 2:]
    x0, y0 = np.maximum(np.floor(proj.min(axis=0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(proj.max(axis=0)).astype(int) + 2, (w, h))
    bw, bh = max(x1 - x0, 0), max(y1 - y0, 0)
    s = int(supersample)
    offs = (np.arange(s) + 0.5) / s - 0.5
    if s % 2 == 0:  # keep the exact pixel centre as an extra sample for the GT maps
        offs_x, offs_y = [a.ravel() for a in np.meshgrid(offs, offs)]
        offs_x, offs_y = np.append(offs_x, 0.0), np.append(offs_y, 0.0)
        n_img, centre = s * s, s * s
    else:
        offs_x, offs_y = [a.ravel() for a in np.meshgrid(offs, offs)]
        n_img, centre = s * s, (s * s) // 2
    m = len(offs_x)
    jj, ii = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    px = (jj[..., None] + offs_x).reshape(-1)
    py = (ii[..., None] + offs_y).reshape(-1)
    Kinv = np.linalg.inv(K)
    dirs = np.stack([px, py, np.ones_like(px)], 1) @ Kinv.T
    t, prim, uvs = scene.cast(np.zeros_like(dirs), dirs)
    hit = np.isfinite(t)
    g = _gather(face, hit, prim, uvs, np.where(hit, t, np.inf), (hit.size, 1))  # dirs have z = 1: t = camera z
    shade = light.rotated(R).shade(g["normals"].reshape(-1, 3) @ R.T)
    colour = g["albedo"].reshape(-1, 3) * shade[:, None]

    if background is None:
        bg = np.full((h, w, 3), 0.5)
    else:
        bg = np.array(np.broadcast_to(np.asarray(background, dtype=np.float64), (h, w, 3)))
    pix = bg.copy()
    box_bg = np.repeat(bg[y0:y1, x0:x1].reshape(-1, 3), m, axis=0)
    samples = np.where(hit[:, None], colour, box_bg).reshape(bh, bw, m, 3)
    pix[y0:y1, x0:x1] = samples[:, :, :n_img].mean(axis=2)
    if noise_sigma > 0:
        if rng is None:
            raise ValueError("noise_sigma > 0 needs an rng")
        pix = pix + rng.normal(0.0, noise_sigma, pix.shape)
    image = np.clip(np.round(pix * 255), 0, 255).astype(np.uint8)

    face_mask = np.zeros((h, w), bool)
    depth = np.full((h, w), np.inf)
    uv = np.full((h, w, 2), np.nan, np.float32)
    face_mask[y0:y1, x0:x1] = hit.reshape(bh, bw, m)[:, :, centre]
    depth[y0:y1, x0:x1] = g["depth"].reshape(bh, bw, m)[:, :, centre]
    uv[y0:y1, x0:x1] = g["uv"].reshape(bh, bw, m, 2)[:, :, centre]

    lm2 = cv2.projectPoints(face.landmarks3d.reshape(-1, 1, 3), rvec, tvec, K, None)[0].reshape(-1, 2)
    lcam = face.landmarks3d @ R.T + tvec
    t_lm, _, _ = scene.cast(np.zeros_like(lcam), lcam)  # the landmark itself is at t = 1
    eps = 1.0 / np.linalg.norm(lcam, axis=1)  # 1 canonical px
    visible = ~(t_lm < 1.0 - eps)
    return SyntheticPhoto(image=image, landmarks=lm2, visible=visible, rvec=rvec, tvec=tvec, camera=K,
                          light=light, expression=face.expression, identity=face.identity,
                          face_mask=face_mask, depth=depth, uv=uv)


def look_at_pose(yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0, *, face_px: float = 110.0,
                 image_size: tuple[int, int] = (250, 250), focal: float | None = None,
                 shift_px: tuple[float, float] = (0.0, 0.0)):
    """Pose placing the face centred in the image, its oval about ``face_px`` wide.

    R = Rz(roll) Ry(yaw) Rx(pitch) (camera axes, right-handed), about a head pivot behind the face
    at canonical (97, 112, 230). The pivot projects to the image centre (plus ``shift_px``).
    focal defaults to 2 * max(h, w). Returns (rvec (3,), tvec (3,), K (3, 3)).
    """
    h, w = image_size
    f = 2.0 * max(h, w) if focal is None else float(focal)
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    a, b, c = np.radians([pitch_deg, yaw_deg, roll_deg])
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    R = Rz @ Ry @ Rx
    d = f * _FACE_WIDTH / face_px + (_PIVOT[2] - _JAW_Z)
    target = np.array([shift_px[0] * d / f, shift_px[1] * d / f, d])
    tvec = target - R @ _PIVOT
    rvec = cv2.Rodrigues(R)[0].ravel()
    return rvec, tvec, K


def random_expression(rng: np.random.Generator, sigma: float = 0.25) -> Expression:
    """smile, open, brow ~ N(0, sigma) clipped to [-1, 1]; blink = max(0, N(0, sigma)) clipped to 1."""
    s, o, b, k = rng.normal(0.0, sigma, 4)
    return Expression(smile=float(np.clip(s, -1, 1)), open=float(np.clip(o, -1, 1)),
                      brow=float(np.clip(b, -1, 1)), blink=float(np.clip(k, 0, 1)))


def make_collection(n: int, *, seed: int, identity: FaceIdentity | None = None,
                    image_size: tuple[int, int] = (250, 250), face_px: float = 110.0,
                    yaw_range: float = 30.0, pitch_range: float = 15.0, roll_range: float = 5.0,
                    expression_sigma: float = 0.25, noise_sigma: float = 0.01,
                    light_fn=None, focal: float | None = None, supersample: int = 2) -> list[SyntheticPhoto]:
    """An in-the-wild-like collection of one identity (ALGORITHMS §3.2 recipes 1, 2 and 4).

    identity None draws one with ``FaceIdentity.random`` from the seed. Poses are uniform within
    +-range (degrees), and the face width and position are jittered by 8 % and 3 %. Expressions come
    from ``random_expression`` (sigma 0 gives the neutral face), lights from ``Light.random``
    (or ``light_fn(rng)``), backgrounds from ``random_background``.
    """
    rng = np.random.default_rng(seed)
    identity = FaceIdentity.random(rng) if identity is None else identity
    photos = []
    for _ in range(n):
        expr = random_expression(rng, expression_sigma) if expression_sigma > 0 else Expression()
        yaw, pitch, roll = rng.uniform(-1, 1, 3) * (yaw_range, pitch_range, roll_range)
        size = face_px * rng.uniform(0.92, 1.08)
        shift = tuple(rng.uniform(-0.03, 0.03, 2) * np.array(image_size[::-1]))
        rvec, tvec, K = look_at_pose(yaw, pitch, roll, face_px=size, image_size=image_size, focal=focal,
                                     shift_px=shift)
        light = light_fn(rng) if light_fn is not None else Light.random(rng)
        bg = random_background(rng, image_size)
        photos.append(render_photo(make_face(identity, expr), rvec=rvec, tvec=tvec, camera=K, light=light,
                                   image_size=image_size, background=bg, noise_sigma=noise_sigma, rng=rng,
                                   supersample=supersample))
    return photos


def _smooth_track(rng: np.random.Generator, n: int, period: tuple[float, float], components: int = 3) -> np.ndarray:
    """A smooth zero-mean trajectory of n samples, amplitude about 1, made of a few random sinusoids."""
    t = np.arange(n)
    out = np.zeros(n)
    for _ in range(components):
        p = rng.uniform(*period)
        out += rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * t / p + rng.uniform(0, 2 * np.pi))
    return out / components * 1.5


def make_driver_video(n_frames: int, *, seed: int, identity: FaceIdentity | None = None,
                      image_size: tuple[int, int] = (256, 256), face_px: float = 140.0,
                      expression_scale: float = 0.8, yaw_amp: float = 10.0, pitch_amp: float = 5.0,
                      roll_amp: float = 3.0, light: Light | None = None, noise_sigma: float = 0.005,
                      focal: float | None = None, supersample: int = 2) -> list[SyntheticPhoto]:
    """A driver video (ALGORITHMS §3.2 recipe 3): smooth expressions, smooth small head motion, fixed light.

    Expression and pose tracks are sums of random sinusoids with periods of 30-120 frames. Blinks
    are short smooth pulses about every 60-120 frames. The GT mesh of frame t is
    ``make_face(identity, photo.expression).verts``.
    """
    rng = np.random.default_rng(seed)
    identity = FaceIdentity.random(rng) if identity is None else identity
    light = Light.random(rng) if light is None else light
    bg = random_background(rng, image_size)
    per = (30.0, 120.0)
    smile = np.clip(expression_scale * _smooth_track(rng, n_frames, per), -1, 1)
    opening = np.clip(expression_scale * (0.5 + _smooth_track(rng, n_frames, per)) * 0.8, -1, 1)
    brow = np.clip(expression_scale * _smooth_track(rng, n_frames, per), -1, 1)
    blink = np.zeros(n_frames)
    t0 = rng.uniform(10, 60)
    t = np.arange(n_frames)
    while t0 < n_frames + 10:
        blink += np.exp(-0.5 * ((t - t0) / 2.0) ** 2)
        t0 += rng.uniform(60, 120)
    blink = np.clip(blink, 0, 1)
    yaw = yaw_amp * _smooth_track(rng, n_frames, (60.0, 150.0))
    pitch = pitch_amp * _smooth_track(rng, n_frames, (60.0, 150.0))
    roll = roll_amp * _smooth_track(rng, n_frames, (60.0, 150.0))
    frames = []
    for i in range(n_frames):
        expr = Expression(float(smile[i]), float(opening[i]), float(brow[i]), float(blink[i]))
        rvec, tvec, K = look_at_pose(yaw[i], pitch[i], roll[i], face_px=face_px, image_size=image_size, focal=focal)
        frames.append(render_photo(make_face(identity, expr), rvec=rvec, tvec=tvec, camera=K, light=light,
                                   image_size=image_size, background=bg, noise_sigma=noise_sigma, rng=rng,
                                   supersample=supersample))
    return frames


# ----------------------------------------------------------------------------- texture ground truth

def smile_crease(identity: FaceIdentity, thickness: int = 2) -> np.ndarray:
    """A smile crease (a nasolabial fold on each side: from beside the nose wing to outside the
    mouth corner) on the canonical parameter grid of ``identity``: (244, 194) bool."""
    lm = make_face(identity).landmarks3d[:, :2]  # neutral: parameter = canonical position
    crease = np.zeros((H, W), np.uint8)
    for wing, corner, side in ((31, 48, -1), (35, 54, 1)):
        top = lm[wing] + (side * 6, -2)
        bottom = lm[corner] + (side * 7, 9)
        cv2.line(crease, tuple(np.round(top).astype(int)), tuple(np.round(bottom).astype(int)), 1, thickness)
    return crease > 0


def crease_collection(n: int, *, seed: int, identity: FaceIdentity | None = None, smile_fraction: float = 0.5,
                      cast: float = 0.15, darkening: float = 0.5, yaw_range: float = 20.0,
                      image_size: tuple[int, int] = (250, 250)) -> tuple[list[SyntheticPhoto], np.ndarray]:
    """Ground truth for expression-dependent texture (ALGORITHMS §12.7 test 2).

    A fraction ``smile_fraction`` of the photos smile (smile 0.7-1), the rest do not (smile
    within ±0.1); only the smiling ones carry :func:`smile_crease` in their albedo (multiplied by
    ``1 - darkening``). Every photo gets a random per-channel colour cast, gains within
    ``1 ± cast``. Returns the photos (``expression`` records the smile) and the crease mask on
    the parameter grid.
    """
    rng = np.random.default_rng(seed)
    identity = FaceIdentity.random(rng) if identity is None else identity
    crease = smile_crease(identity)
    photos = []
    for i in range(n):
        smiling = i < round(smile_fraction * n)
        expr = Expression(smile=float(rng.uniform(0.7, 1.0) if smiling else rng.uniform(-0.1, 0.1)),
                          open=float(rng.uniform(0, 0.2)))
        face = make_face(identity, expr)
        if smiling:
            face.vert_albedo = np.where(crease[..., None], face.vert_albedo * (1 - darkening), face.vert_albedo)
        yaw, pitch = rng.uniform(-1, 1, 2) * (yaw_range, 10.0)
        rvec, tvec, K = look_at_pose(yaw, pitch, 0.0, face_px=110 * rng.uniform(0.95, 1.05), image_size=image_size)
        photo = render_photo(face, rvec=rvec, tvec=tvec, camera=K, light=Light.random(rng), image_size=image_size,
                             background=random_background(rng, image_size), noise_sigma=0.01, rng=rng,
                             supersample=2)
        gains = rng.uniform(1 - cast, 1 + cast, 3)
        photo.image = np.clip(photo.image * gains, 0, 255).round().astype(np.uint8)
        photos.append(photo)
    order = rng.permutation(n)  # smiling and neutral photos interleaved
    return [photos[i] for i in order], crease
