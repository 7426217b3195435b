"""Dense optical flow backends (kind ``flow``, ALGORITHMS §6).

Every backend returns ``w`` of shape (H, W, 2), float32, channels (dx, dy), on image0's
grid, with ``image0(x) ≈ image1(x + w(x))`` (the OpenCV / Ce Liu convention, ALGORITHMS §0).

* ``liu``: a faithful port of Ce Liu's ``Coarse2FineTwoFrames`` (Brox et al. 2004 energy
  solved as in Bruhn et al. 2005), the flow the paper uses, compiled with numba;
* ``dis``, ``tvl1``, ``deepflow``, ``farneback``: OpenCV's flows;
* ``varref``: a coarse-to-fine pyramid (Liu's ratio and minimum width) over OpenCV's
  single-level ``cv2.VariationalRefinement``.

The input checks, the mask filling and the grey / 8-bit conversions are the public helpers
:func:`prepare_pair`, :func:`fill_outside_mask`, :func:`to_grey` and :func:`to_uint8_pair`,
which third-party flow backends may reuse.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numba
import numpy as np
from pydantic import ConfigDict, Field, model_validator

from ..base import Params
from ..hookspecs import hookimpl
from ..kinds import FlowBackend

#: smallest image side the backends accept
MIN_SIDE = 8


# ----------------------------------------------------------------------------------------
# input handling shared by every backend
# ----------------------------------------------------------------------------------------


def _as_float_image(image, name: str) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype == np.uint8:
        a = a.astype(np.float64) / 255.0
    elif a.dtype == np.uint16:
        a = a.astype(np.float64) / 65535.0
    elif np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    else:
        raise ValueError(f"flow: {name} must be float in [0, 1] or uint8, got dtype {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 2:
        a = a[:, :, None]
    elif not (a.ndim == 3 and a.shape[2] == 3):
        raise ValueError(f"flow: {name} must have shape (H, W) or (H, W, 3), got {a.shape}")
    if a.shape[0] < MIN_SIDE or a.shape[1] < MIN_SIDE:
        raise ValueError(f"flow: {name} is {a.shape[0]}x{a.shape[1]} px; each side must be "
                         f">= {MIN_SIDE} px")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"flow: {name} has NaN or infinite values")
    return np.ascontiguousarray(a)


def prepare_pair(image0, image1, mask=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Check and convert a pair: returns (i0, i1, mask) with i0, i1 float64 (H, W, C), C = 1 or 3,
    in [0, 1] when the input was, and mask (H, W) bool or None. Raises ValueError on bad input."""
    i0 = _as_float_image(image0, "image0")
    i1 = _as_float_image(image1, "image1")
    if i0.shape != i1.shape:
        raise ValueError(f"flow: image0 and image1 must have the same shape, got "
                         f"{np.shape(image0)} and {np.shape(image1)}")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != i0.shape[:2]:
            raise ValueError(f"flow: mask must have shape {i0.shape[:2]} (image0's H, W), "
                             f"got {mask.shape}")
        if mask.dtype != bool:
            if not (np.issubdtype(mask.dtype, np.integer) or np.issubdtype(mask.dtype, np.floating)):
                raise ValueError(f"flow: mask must be bool, got dtype {mask.dtype}")
            mask = mask > 0.5 if np.issubdtype(mask.dtype, np.floating) else mask != 0
    return i0, i1, mask


def _wide_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur; beyond σ = 8 px computed at a resolution reduced to keep σ at 4 px there
    (the same smooth result for a fill, without kernels hundreds of pixels wide)."""
    if sigma <= 8:
        return cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    h, w = image.shape[:2]
    factor = sigma / 4
    small = cv2.resize(image, (max(1, round(w / factor)), max(1, round(h / factor))), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 4.0, borderType=cv2.BORDER_REPLICATE)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def fill_outside_mask(image: np.ndarray, mask: np.ndarray, sigma: float = 4.0) -> np.ndarray:
    """image (H, W, C) float64 with the pixels outside ``mask`` replaced by a smooth, texture-free
    extension of the masked values (normalised Gaussian convolution, widened until every pixel is
    reached). The pair then has no mask edge for the flow to latch onto (ALGORITHMS §6.5): outside
    the mask the data term is ~0 and the smoothness term extends the flow from inside."""
    if mask.all():
        return image
    h, w, c = image.shape
    if not mask.any():
        return np.broadcast_to(image.reshape(-1, c).mean(0), image.shape).copy()
    m = mask.astype(np.float64)
    weighted = image * m[:, :, None]
    fill = np.zeros_like(image)
    done = mask.copy()
    s = sigma
    while True:
        den = _wide_blur(m, s)
        num = _wide_blur(weighted, s).reshape(h, w, c)
        new = (den > 1e-3) & ~done
        fill[new] = num[new] / den[new][:, None]
        done |= new
        if done.all():
            break
        s *= 2
        if s > 4 * max(h, w):
            fill[~done] = image[mask].mean(0)
            break
    return np.where(mask[:, :, None], image, fill)


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> (H, W) float64 grey (Rec. 601 weights for RGB, as Liu's ``desaturate``)."""
    if image.shape[2] == 1:
        return image[:, :, 0]
    return image[:, :, 0] * 0.299 + image[:, :, 1] * 0.587 + image[:, :, 2] * 0.114


def _stretched(g0: np.ndarray, g1: np.ndarray, stretch: bool) -> tuple[np.ndarray, np.ndarray]:
    """Two grey float images in [0, 255] units, float64. With ``stretch``, the pair's joint
    range is mapped to [0, 255] (one affine map for both, so the flow is unchanged and
    low-contrast texture is not lost to quantisation); otherwise [0, 1] -> [0, 255]."""
    lo, hi = 0.0, 1.0
    if stretch:
        lo = min(g0.min(), g1.min())
        hi = max(g0.max(), g1.max())
        if hi - lo < 1e-12:
            lo, hi = lo - 0.5, lo + 0.5
    scale = 255.0 / (hi - lo)
    return (g0 - lo) * scale, (g1 - lo) * scale


def to_uint8_pair(g0: np.ndarray, g1: np.ndarray, stretch: bool) -> tuple[np.ndarray, np.ndarray]:
    """Two grey float images -> uint8, mapped as :func:`_stretched` maps them."""
    q = [np.clip(np.rint(g), 0, 255).astype(np.uint8) for g in _stretched(g0, g1, stretch)]
    return q[0], q[1]


def to_float255_pair(g0: np.ndarray, g1: np.ndarray, stretch: bool) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`to_uint8_pair` but float32 without quantisation."""
    f0, f1 = _stretched(g0, g1, stretch)
    return f0.astype(np.float32), f1.astype(np.float32)


def _prepared(image0, image1, mask):
    """prepare_pair + mask filling: (i0, i1) float64 (H, W, C), or None for an empty mask."""
    i0, i1, m = prepare_pair(image0, image1, mask)
    if m is not None:
        if not m.any():
            return None
        i0 = fill_outside_mask(i0, m)
        i1 = fill_outside_mask(i1, m)
    return i0, i1


def _finish(flow: np.ndarray) -> np.ndarray:
    out = np.ascontiguousarray(flow, dtype=np.float32)
    if not np.all(np.isfinite(out)):  # never hand back NaN: the DAG would store it
        out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    return out


# ----------------------------------------------------------------------------------------
# Ce Liu's Coarse2FineTwoFrames, ported from OpticalFlow.cpp / GaussianPyramid.cpp.
# Arrays are (C, H, W) float64. Borders are replicated as in Liu's ImageProcessing.h.
# ----------------------------------------------------------------------------------------

_DERIV5 = np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12.0  # Image::dx(..., advanced=true)
_SMOOTH5 = np.array([0.02, 0.11, 0.74, 0.11, 0.02])  # getDxs's gfilter
_IDENT1 = np.ones(1)


def pyramid_levels(width: int, ratio: float, min_width: int) -> int:
    """Liu's level count: ``int(log(minWidth / width) / log(ratio))`` (at least 1).
    13 for width 194, ratio 0.85, min_width 20 (ALGORITHMS §6.2)."""
    n = int(math.log(min_width / width) / math.log(ratio))
    return max(1, n)


@numba.njit(cache=True, nogil=True)
def _filter_h(src, k):
    """Horizontal 1-D filter, borders replicated (Liu's hfiltering)."""
    c_, h, w = src.shape
    f = (k.size - 1) // 2
    out = np.empty_like(src)
    five = k.size == 5
    if five:
        k0, k1, k2, k3, k4 = k[0], k[1], k[2], k[3], k[4]
    for c in range(c_):
        for i in range(h):
            row = src[c, i]
            orow = out[c, i]
            if five:
                for j in range(2, w - 2):
                    orow[j] = (k0 * row[j - 2] + k1 * row[j - 1] + k2 * row[j]
                               + k3 * row[j + 1] + k4 * row[j + 2])
            for j in range(w):
                if not five or j < f or j >= w - f:
                    s = 0.0
                    for l in range(-f, f + 1):
                        jj = min(max(j + l, 0), w - 1)
                        s += row[jj] * k[l + f]
                    orow[j] = s
    return out


@numba.njit(cache=True, nogil=True)
def _filter_v(src, k):
    c_, h, w = src.shape
    f = (k.size - 1) // 2
    out = np.zeros_like(src)
    for c in range(c_):
        for i in range(h):
            for l in range(-f, f + 1):
                ii = min(max(i + l, 0), h - 1)
                kl = k[l + f]
                for j in range(w):
                    out[c, i, j] += src[c, ii, j] * kl
    return out


@numba.njit(cache=True, nogil=True)
def _bilinear(img, c, x, y):
    """Liu's BilinearInterpolate: truncation, clamped corners."""
    h = img.shape[1]
    w = img.shape[2]
    xx = int(x)
    yy = int(y)
    dx = min(max(x - xx, 0.0), 1.0)
    dy = min(max(y - yy, 0.0), 1.0)
    x0 = min(max(xx, 0), w - 1)
    x1 = min(max(xx + 1, 0), w - 1)
    y0 = min(max(yy, 0), h - 1)
    y1 = min(max(yy + 1, 0), h - 1)
    return ((1 - dx) * (1 - dy) * img[c, y0, x0] + dx * (1 - dy) * img[c, y0, x1]
            + (1 - dx) * dy * img[c, y1, x0] + dx * dy * img[c, y1, x1])


@numba.njit(cache=True, nogil=True)
def _resize(src, dh, dw, ry, rx):
    """Liu's ResizeImage: destination (j, i) samples source ((j+1)/rx - 1, (i+1)/ry - 1)."""
    c_ = src.shape[0]
    out = np.empty((c_, dh, dw))
    for c in range(c_):
        for i in range(dh):
            y = (i + 1) / ry - 1.0
            for j in range(dw):
                x = (j + 1) / rx - 1.0
                out[c, i, j] = _bilinear(src, c, x, y)
    return out


@numba.njit(cache=True, nogil=True)
def _warp(im1, im2, u, v, liu_outside):
    """Liu's warpImage: im2 sampled at x + w (bilinear). Where x + w leaves the image, Liu copies
    im1's value (``liu_outside``); otherwise im2's border is replicated."""
    c_, h, w = im2.shape
    out = np.empty_like(im2)
    for i in range(h):
        for j in range(w):
            x = j + u[i, j]
            y = i + v[i, j]
            if liu_outside and (x < 0 or x > w - 1 or y < 0 or y > h - 1):
                for c in range(c_):
                    out[c, i, j] = im1[c, i, j]
            else:
                for c in range(c_):
                    out[c, i, j] = _bilinear(im2, c, x, y)
    return out


@numba.njit(cache=True, nogil=True)
def _im2feature(im, deriv):
    """Liu's im2feature: grey -> [I, I_x, I_y]; RGB -> [gray, gray_x, gray_y, G-R, G-B]."""
    c_, h, w = im.shape
    if c_ == 1:
        grey = im.copy()
    else:
        grey = np.empty((1, h, w))
        for i in range(h):
            for j in range(w):
                grey[0, i, j] = im[0, i, j] * 0.299 + im[1, i, j] * 0.587 + im[2, i, j] * 0.114
    gx = _filter_h(grey, deriv)
    gy = _filter_v(grey, deriv)
    nf = 3 if c_ == 1 else 5
    out = np.empty((nf, h, w))
    out[0] = grey[0]
    out[1] = gx[0]
    out[2] = gy[0]
    if c_ == 3:
        for i in range(h):
            for j in range(w):
                out[3, i, j] = im[1, i, j] - im[0, i, j]
                out[4, i, j] = im[1, i, j] - im[2, i, j]
    return out


@numba.njit(cache=True, nogil=True)
def _sor(phi, a11, a12, a22, b1, b2, alpha, omega, n_sor, coef, duv):
    """n_sor lexicographic SOR sweeps of Liu's SmoothFlowSOR from (du, dv) = 0; the result is
    left in duv[1:-1, 1:-1] (zero-padded (H + 2, W + 2, 2)).

    Same update as Liu's, with the coefficients divided by the diagonal once per call and the
    just-updated left neighbour added last, so the sweep's serial dependency is one multiply-add
    per pixel (it is latency-bound otherwise)."""
    h, w = phi.shape
    damp = alpha * 0.05
    for i in range(h):
        for j in range(w):
            cl = alpha * phi[i, j - 1] if j > 0 else 0.0
            cr = alpha * phi[i, j] if j < w - 1 else 0.0
            cu = alpha * phi[i - 1, j] if i > 0 else 0.0
            cd = alpha * phi[i, j] if i < h - 1 else 0.0
            s = cl + cr + cu + cd
            g1 = omega / (a11[i, j] + damp + s)
            g2 = omega / (a22[i, j] + damp + s)
            coef[i, j, 0] = g1 * cl
            coef[i, j, 1] = g1 * cr
            coef[i, j, 2] = g1 * cu
            coef[i, j, 3] = g1 * cd
            coef[i, j, 4] = g1 * b1[i, j]
            coef[i, j, 5] = g1 * a12[i, j]
            coef[i, j, 6] = g2 * cl
            coef[i, j, 7] = g2 * cr
            coef[i, j, 8] = g2 * cu
            coef[i, j, 9] = g2 * cd
            coef[i, j, 10] = g2 * b2[i, j]
            coef[i, j, 11] = g2 * a12[i, j]
    duv[:, :, :] = 0.0
    keep = 1.0 - omega
    for _k in range(n_sor):
        for i in range(h):
            ii = i + 1
            du_left = 0.0
            dv_left = 0.0
            for j in range(w):
                jj = j + 1
                c = coef[i, j]
                duo = duv[ii, jj, 0]
                dvo = duv[ii, jj, 1]
                pu = (keep * duo + c[4] + c[1] * duv[ii, jj + 1, 0] + c[2] * duv[ii - 1, jj, 0]
                      + c[3] * duv[ii + 1, jj, 0] - c[5] * dvo)
                dun = pu + c[0] * du_left
                pv = (keep * dvo + c[10] + c[7] * duv[ii, jj + 1, 1] + c[8] * duv[ii - 1, jj, 1]
                      + c[9] * duv[ii + 1, jj, 1])
                dvn = (pv - c[11] * dun) + c[6] * dv_left
                duv[ii, jj, 0] = dun
                duv[ii, jj, 1] = dvn
                du_left = dun
                dv_left = dvn


@numba.njit(cache=True, nogil=True)
def _smooth_flow_sor(im1, im2, u, v, alpha, n_outer, n_inner, n_sor, smooth, deriv, liu_outside):
    """Liu's SmoothFlowSOR for one pyramid level; u, v (H, W) are updated in place."""
    c_, h, w = im1.shape
    eps_phi = 0.001 ** 2
    eps_psi = 0.001 ** 2
    omega = 1.8
    du = np.zeros((h, w))
    dv = np.zeros((h, w))
    phi = np.zeros((h, w))
    a11 = np.zeros((h, w))
    a12 = np.zeros((h, w))
    a22 = np.zeros((h, w))
    b1 = np.zeros((h, w))
    b2 = np.zeros((h, w))
    coef = np.zeros((h, w, 12))
    duv = np.zeros((h + 2, w + 2, 2))
    warp2 = _warp(im1, im2, u, v, liu_outside)
    i1s = _filter_v(_filter_h(im1, smooth), smooth)
    for _outer in range(n_outer):
        # getDxs: smooth both, derivatives of 0.4*I1s + 0.6*I2s, temporal I2s - I1s
        i2s = _filter_v(_filter_h(warp2, smooth), smooth)
        mix = 0.4 * i1s + 0.6 * i2s
        imdx = _filter_h(mix, deriv)
        imdy = _filter_v(mix, deriv)
        imdt = i2s - i1s
        du[:, :] = 0.0
        dv[:, :] = 0.0
        for hh in range(n_inner):
            # phi' of the smoothness term, forward differences of u + du (zero at the last col/row)
            for i in range(h):
                for j in range(w):
                    uc = u[i, j] + du[i, j]
                    vc = v[i, j] + dv[i, j]
                    ux = 0.0
                    vx = 0.0
                    uy = 0.0
                    vy = 0.0
                    if j < w - 1:
                        ux = u[i, j + 1] + du[i, j + 1] - uc
                        vx = v[i, j + 1] + dv[i, j + 1] - vc
                    if i < h - 1:
                        uy = u[i + 1, j] + du[i + 1, j] - uc
                        vy = v[i + 1, j] + dv[i + 1, j] - vc
                    phi[i, j] = 0.5 / math.sqrt(ux * ux + uy * uy + vx * vx + vy * vy + eps_phi)
            # psi' of the data term per channel, and the per-pixel 2x2 systems
            for i in range(h):
                for j in range(w):
                    s11 = 0.0
                    s12 = 0.0
                    s22 = 0.0
                    st1 = 0.0
                    st2 = 0.0
                    for c in range(c_):
                        ix = imdx[c, i, j]
                        iy = imdy[c, i, j]
                        it = imdt[c, i, j]
                        r = it + ix * du[i, j] + iy * dv[i, j]
                        psi = 1.0 / (2.0 * math.sqrt(r * r + eps_psi))
                        s11 += psi * ix * ix
                        s12 += psi * ix * iy
                        s22 += psi * iy * iy
                        st1 += psi * ix * it
                        st2 += psi * iy * it
                    a11[i, j] = s11
                    a12[i, j] = s12
                    a22[i, j] = s22
                    b1[i, j] = -st1
                    b2[i, j] = -st2
            # b -= alpha * L_phi(u), L_phi u = -div(phi grad u) (Liu's Laplacian, on u not u + du)
            for i in range(h):
                for j in range(w):
                    lu = 0.0
                    lv = 0.0
                    if j < w - 1:
                        lu -= (u[i, j + 1] - u[i, j]) * phi[i, j]
                        lv -= (v[i, j + 1] - v[i, j]) * phi[i, j]
                    if j > 0:
                        lu += (u[i, j] - u[i, j - 1]) * phi[i, j - 1]
                        lv += (v[i, j] - v[i, j - 1]) * phi[i, j - 1]
                    if i < h - 1:
                        lu -= (u[i + 1, j] - u[i, j]) * phi[i, j]
                        lv -= (v[i + 1, j] - v[i, j]) * phi[i, j]
                    if i > 0:
                        lu += (u[i, j] - u[i - 1, j]) * phi[i - 1, j]
                        lv += (v[i, j] - v[i - 1, j]) * phi[i - 1, j]
                    b1[i, j] -= alpha * lu
                    b2[i, j] -= alpha * lv
            # SOR, lexicographic Gauss-Seidel with omega = 1.8, as Liu. The per-pixel
            # coefficients are packed once and (du, dv) is zero-padded, so the sweep has no branch.
            _sor(phi, a11, a12, a22, b1, b2, alpha, omega, n_sor, coef, duv)
            for i in range(h):
                for j in range(w):
                    du[i, j] = duv[i + 1, j + 1, 0]
                    dv[i, j] = duv[i + 1, j + 1, 1]
        for i in range(h):
            for j in range(w):
                u[i, j] += du[i, j]
                v[i, j] += dv[i, j]
        warp2 = _warp(im1, im2, u, v, liu_outside)


def _gaussian_kernel(sigma: float) -> np.ndarray:
    """Liu's GaussianSmoothing kernel: radius int(3 sigma), normalised."""
    f = int(sigma * 3)
    x = np.arange(-f, f + 1, dtype=np.float64)
    k = np.exp(-(x * x) / (2 * sigma * sigma))
    return k / k.sum()


def _pyramid(image: np.ndarray, ratio: float, n_levels: int) -> list[np.ndarray]:
    """Liu's GaussianPyramid::ConstructPyramid (the fast way), image (C, H, W)."""
    levels = [image]
    base_sigma = 1 / ratio - 1
    n = int(math.log(0.25) / math.log(ratio))
    n_sigma = base_sigma * n
    w0 = image.shape[2]
    for i in range(1, n_levels):
        if i <= n:
            k = _gaussian_kernel(base_sigma * i)
            src, rate = image, ratio ** i
        else:
            k = _gaussian_kernel(n_sigma)
            src = levels[i - n]
            rate = ratio ** i * w0 / src.shape[2]
        smooth = _filter_v(_filter_h(src, k), k)
        dh, dw = int(src.shape[1] * rate), int(src.shape[2] * rate)
        if dh < 2 or dw < 2:
            break
        levels.append(_resize(smooth, dh, dw, rate, rate))
    return levels


def coarse2fine_flow(im1: np.ndarray, im2: np.ndarray, alpha: float, ratio: float, min_width: int,
                     n_outer: int, n_inner: int, n_sor: int, outside: str = "replicate"
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Liu's Coarse2FineFlow on (C, H, W) float64 images in [0, 1], C = 1 or 3: returns (vx, vy).
    ``outside`` is LiuFlow.Params.outside."""
    n_levels = pyramid_levels(im1.shape[2], ratio, min_width)
    p1 = _pyramid(im1, ratio, n_levels)
    p2 = _pyramid(im2, ratio, n_levels)
    u = v = None
    for k in range(len(p1) - 1, -1, -1):
        f1 = _im2feature(p1[k], _DERIV5)
        f2 = _im2feature(p2[k], _DERIV5)
        h, w = f1.shape[1:]
        if u is None:
            u = np.zeros((h, w))
            v = np.zeros((h, w))
        else:  # Liu: imresize to the new size, then multiply by 1/ratio
            u = _resize(u[None], h, w, h / u.shape[0], w / u.shape[1])[0] / ratio
            v = _resize(v[None], h, w, h / v.shape[0], w / v.shape[1])[0] / ratio
        _smooth_flow_sor(f1, f2, u, v, alpha, n_outer + k, n_inner, n_sor + 3 * k, _SMOOTH5, _DERIV5,
                         outside == "image0")
    return u, v


class PreparedFlow(FlowBackend):
    """The built-ins' common entry: inputs checked and converted, the outside of the mask
    filled (ALGORITHMS §6.5); subclasses implement ``compute`` on the prepared pair."""

    version = "2"  # 2: the mask fill's wide blurs at reduced resolution

    def flow(self, image0, image1, mask=None):
        pair = _prepared(image0, image1, mask)
        if pair is None:  # an empty mask: nothing to align
            return np.zeros(np.shape(image0)[:2] + (2,), np.float32)
        return self.compute(*pair)

    def compute(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        """image0, image1: (H, W, C) float64 in [0, 1], masks already filled -> (H, W, 2) float32."""
        raise NotImplementedError


class LiuFlow(PreparedFlow):
    """Ce Liu's ``Coarse2FineTwoFrames`` (OpticalFlow.cpp, GaussianPyramid.cpp), ALGORITHMS §6.1-6.2.

    Kept from Liu: feature channels (im2feature, [1,-8,0,8,-1]/12 derivatives), the
    [0.02, 0.11, 0.74, 0.11, 0.02] smoothing and 0.4/0.6 mix of getDxs, Charbonnier
    (ε = 0.001) data and smoothness weights lagged per inner iteration, forward differences,
    the α·0.05 damping, lexicographic SOR with ω = 1.8, the pyramid (level count, σ and
    resampling rules, borders replicated), nOuter + k / nSOR + 3k per level, and the flow
    upsampled by Liu's bilinear resize and multiplied by 1/ratio.

    Differences: (1) ``outside="replicate"`` (default) samples image1's replicated border where
    x + w leaves the image; Liu copies image0's value there (``outside="image0"``), which makes
    leaving the image free and lets the flow run out of the image under a brightness change.
    (2) The SOR update is Liu's, with its coefficients divided by the diagonal once per call
    (same arithmetic up to rounding; tests compare it with a literal transcription).
    (3) Liu silently replaces a ratio outside [0.4, 0.98] by 0.75; here any ratio in (0, 1) is used.
    (4) Grey images with a global brightness offset are not handled well (0.3 px mean flow for
    +0.05): the intensity channel weighs as much as the two gradient channels. RGB input adds
    the offset-free G-R, G-B channels and stays near 0.
    """

    name = "liu"
    description = ("Ce Liu's Coarse2FineTwoFrames (Brox 2004 energy with Charbonnier data and "
                   "smoothness terms, Bruhn 2005 solver), as used by the paper; numba port")

    class Params(Params):
        alpha: float = Field(0.02, gt=0, description="alpha: weight of the smoothness term "
                             "(paper: 0.02 for driver/puppet correspondence, 0.3 for dense warping)")
        ratio: float = Field(0.85, gt=0, lt=1, description="ratio: downsampling factor between "
                             "pyramid levels (paper: 0.85)")
        min_width: int = Field(20, ge=4, description="minWidth: width of the coarsest pyramid level "
                               "in px; levels = int(log(minWidth/width)/log(ratio)) (paper: 20)")
        outer: int = Field(4, ge=1, le=100, description="nOuterFPIterations: outer fixed-point "
                           "(warping) iterations at the finest level; level k runs outer + k (paper: 4)")
        inner: int = Field(1, ge=1, le=100, description="nInnerFPIterations: inner fixed-point "
                           "iterations re-linearising the robust weights (paper: 1)")
        outside: Literal["replicate", "image0"] = Field(
            "replicate", description="where x + w leaves the image, image1 is sampled at its "
            "replicated border ('replicate'), or replaced by image0's value as in Liu's warpImage "
            "('image0'). The latter makes leaving the image free of data cost, so under a brightness "
            "change between the images the flow near the borders runs out of the image")
        sor: int = Field(40, ge=1, le=1000, description="nSORIterations: SOR sweeps per inner "
                         "iteration at the finest level; level k runs sor + 3k (paper: 40)")

    def compute(self, image0, image1):
        i0, i1 = image0, image1
        p = self.params
        u, v = coarse2fine_flow(np.ascontiguousarray(i0.transpose(2, 0, 1)),
                                np.ascontiguousarray(i1.transpose(2, 0, 1)),
                                p.alpha, p.ratio, p.min_width, p.outer, p.inner, p.sor, p.outside)
        return _finish(np.stack([u, v], axis=-1))


# ----------------------------------------------------------------------------------------
# OpenCV backends
# ----------------------------------------------------------------------------------------

_DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


class DISFlow(PreparedFlow):
    name = "dis"
    description = ("OpenCV DIS (Kroeger et al. 2016) on 8-bit grey, with its built-in variational "
                   "refinement; fast")
    #: the default: 17x faster than liu at the same accuracy on the conformance warps, which
    #: keeps collection flow of hundreds of photos within minutes on two cores
    default = True

    class Params(Params):
        preset: Literal["ultrafast", "fast", "medium"] = Field(
            "medium", description="cv2.DISOpticalFlow preset; the fields below left at None keep "
            "the preset's value")
        finest_scale: int | None = Field(0, ge=0, le=10, description="finest pyramid scale "
                                         "patches are matched at (0 = full resolution; the presets' "
                                         "1-2 give EPE 0.12-0.37 px on the 3 px test warp)")
        patch_size: int | None = Field(None, ge=3, le=64, description="patch size in px")
        patch_stride: int | None = Field(None, ge=1, le=32, description="stride between patches in px")
        gradient_descent_iterations: int | None = Field(None, ge=1, le=1000, description=
                                                        "inverse-search gradient-descent iterations "
                                                        "per patch")
        refinement_alpha: float | None = Field(None, ge=0, description="variational refinement: "
                                               "smoothness weight (alpha)")
        refinement_delta: float | None = Field(None, ge=0, description="variational refinement: "
                                               "colour constancy weight (delta)")
        refinement_gamma: float | None = Field(None, ge=0, description="variational refinement: "
                                               "gradient constancy weight (gamma)")
        refinement_iterations: int | None = Field(None, ge=0, le=1000, description="variational "
                                                  "refinement fixed-point iterations per scale "
                                                  "(0 = off)")
        mean_normalization: bool = Field(True, description="normalise patch means (robust to "
                                         "brightness changes)")
        spatial_propagation: bool = Field(True, description="spatial propagation of patch flows")
        stretch: bool = Field(True, description="map the pair's joint intensity range to [0, 255] "
                              "before quantising to 8 bits (keeps low-contrast texture)")

        @model_validator(mode="after")
        def _stride_within_patch(self):
            if (self.patch_size is not None and self.patch_stride is not None
                    and self.patch_stride > self.patch_size):
                raise ValueError(f"patch_stride ({self.patch_stride}) must not exceed "
                                 f"patch_size ({self.patch_size})")
            return self

    def compute(self, image0, image1):
        p = self.params
        g0, g1 = to_uint8_pair(to_grey(image0), to_grey(image1), p.stretch)
        dis = cv2.DISOpticalFlow.create(_DIS_PRESETS[p.preset])
        for value, setter in ((p.finest_scale, dis.setFinestScale),
                              (p.patch_size, dis.setPatchSize),
                              (p.patch_stride, dis.setPatchStride),
                              (p.gradient_descent_iterations, dis.setGradientDescentIterations),
                              (p.refinement_alpha, dis.setVariationalRefinementAlpha),
                              (p.refinement_delta, dis.setVariationalRefinementDelta),
                              (p.refinement_gamma, dis.setVariationalRefinementGamma),
                              (p.refinement_iterations, dis.setVariationalRefinementIterations)):
            if value is not None:
                setter(value)
        dis.setPatchStride(min(dis.getPatchStride(), dis.getPatchSize()))
        dis.setUseMeanNormalization(p.mean_normalization)
        dis.setUseSpatialPropagation(p.spatial_propagation)
        h, w = g0.shape
        ph, pw = max(0, 16 - h), max(0, 16 - w)  # DIS wants a side >= 12 px: pad tiny images
        if ph or pw:
            g0, g1 = (cv2.copyMakeBorder(g, 0, ph, 0, pw, cv2.BORDER_REFLECT) for g in (g0, g1))
        return _finish(dis.calc(g0, g1, None)[:h, :w])


class TVL1Flow(PreparedFlow):
    name = "tvl1"
    description = "OpenCV dual TV-L1 (Zach et al. 2007; Wedel et al. 2009) on grey, brightness constancy only"

    class Params(Params):
        tau: float = Field(0.25, gt=0, le=0.25, description="tau: time step of the numerical scheme")
        lambda_: float = Field(0.15, gt=0, alias="lambda", description="lambda: weight of the data "
                               "term (larger = less smoothing)")
        theta: float = Field(0.3, gt=0, description="theta: coupling of the two variables")
        scales: int = Field(5, ge=1, le=20, description="number of pyramid scales")
        warps: int = Field(3, ge=1, le=50, description="warpings per scale (OpenCV default 5)")
        epsilon: float = Field(0.01, gt=0, description="stopping threshold per warp")
        inner_iterations: int = Field(10, ge=1, le=1000, description="inner iterations (OpenCV "
                                      "default 30)")
        outer_iterations: int = Field(2, ge=1, le=1000, description="outer iterations (OpenCV "
                                      "default 10; with OpenCV's defaults a 194x244 pair takes ~5 s)")
        scale_step: float = Field(0.8, gt=0, lt=1, description="downsampling step between scales")
        gamma: float = Field(0.0, ge=0, description="gamma: weight of the illumination-variation "
                             "term (0 = off)")
        median_filtering: int = Field(5, ge=1, le=7, description="median filter size on the flow "
                                      "(1 = off)")
        stretch: bool = Field(True, description="map the pair's joint intensity range to [0, 255]")

        model_config = ConfigDict(populate_by_name=True)

    def compute(self, image0, image1):
        p = self.params
        g0, g1 = to_float255_pair(to_grey(image0), to_grey(image1), p.stretch)
        tv = cv2.optflow.DualTVL1OpticalFlow_create(
            tau=p.tau, lambda_=p.lambda_, theta=p.theta, nscales=p.scales, warps=p.warps,
            epsilon=p.epsilon, innnerIterations=p.inner_iterations,
            outerIterations=p.outer_iterations, scaleStep=p.scale_step, gamma=p.gamma,
            medianFiltering=p.median_filtering, useInitialFlow=False)
        return _finish(tv.calc(g0, g1, None))


class DeepFlow(PreparedFlow):
    name = "deepflow"
    description = ("OpenCV DeepFlow (Weinzaepfel et al. 2013) variational flow on 8-bit grey; "
                   "OpenCV's Python binding exposes no parameters")

    class Params(Params):
        stretch: bool = Field(True, description="map the pair's joint intensity range to [0, 255] "
                              "before quantising to 8 bits")

    def compute(self, image0, image1):
        g0, g1 = to_uint8_pair(to_grey(image0), to_grey(image1), self.params.stretch)
        return _finish(cv2.optflow.createOptFlow_DeepFlow().calc(g0, g1, None))


class FarnebackFlow(PreparedFlow):
    name = "farneback"
    description = "OpenCV Farneback (2003) polynomial-expansion flow on grey"

    class Params(Params):
        pyr_scale: float = Field(0.5, gt=0, lt=1, description="pyr_scale: downsampling between levels")
        levels: int = Field(4, ge=1, le=20, description="levels: number of pyramid levels")
        winsize: int = Field(15, ge=3, le=101, description="winsize: averaging window size in px")
        iterations: int = Field(5, ge=1, le=100, description="iterations per level")
        poly_n: int = Field(5, ge=3, le=11, description="poly_n: neighbourhood of the polynomial "
                            "expansion (5 or 7)")
        poly_sigma: float = Field(1.1, gt=0, description="poly_sigma: Gaussian sigma of the "
                                  "polynomial expansion (1.1 for poly_n 5, 1.5 for 7)")
        gaussian_window: bool = Field(True, description="Gaussian instead of box averaging window "
                                      "(OPTFLOW_FARNEBACK_GAUSSIAN)")
        stretch: bool = Field(True, description="map the pair's joint intensity range to [0, 255]")

    def compute(self, image0, image1):
        p = self.params
        g0, g1 = to_float255_pair(to_grey(image0), to_grey(image1), p.stretch)
        flags = cv2.OPTFLOW_FARNEBACK_GAUSSIAN if p.gaussian_window else 0
        return _finish(cv2.calcOpticalFlowFarneback(g0, g1, None, p.pyr_scale, p.levels, p.winsize,
                                                    p.iterations, p.poly_n, p.poly_sigma, flags))


class VariationalRefinementFlow(PreparedFlow):
    name = "varref"
    description = ("coarse-to-fine pyramid (Liu's ratio and minWidth) over OpenCV's single-level "
                   "Brox-type cv2.VariationalRefinement, on grey in [0, 255]")

    class Params(Params):
        ratio: float = Field(0.85, gt=0, lt=1, description="ratio: downsampling between levels")
        min_width: int = Field(20, ge=4, description="minWidth: coarsest level width in px")
        alpha: float = Field(20.0, gt=0, description="alpha: smoothness weight (data terms are "
                             "gradient-normalised, so not comparable to Liu's alpha)")
        delta: float = Field(5.0, ge=0, description="delta: colour constancy weight")
        gamma: float = Field(10.0, ge=0, description="gamma: gradient constancy weight")
        iterations: int = Field(5, ge=1, le=1000, description="fixed-point iterations per level")
        sor_iterations: int = Field(5, ge=1, le=1000, description="SOR iterations per fixed-point "
                                    "iteration")
        omega: float = Field(1.6, gt=0, lt=2, description="SOR relaxation factor")
        stretch: bool = Field(True, description="map the pair's joint intensity range to [0, 255]")

    def compute(self, image0, image1):
        p = self.params
        g0, g1 = to_float255_pair(to_grey(image0), to_grey(image1), p.stretch)
        h0, w0 = g0.shape
        n_levels = pyramid_levels(w0, p.ratio, p.min_width)
        vr = cv2.VariationalRefinement.create()
        vr.setAlpha(p.alpha)
        vr.setDelta(p.delta)
        vr.setGamma(p.gamma)
        vr.setFixedPointIterations(p.iterations)
        vr.setSorIterations(p.sor_iterations)
        vr.setOmega(p.omega)
        flow = None
        for k in range(n_levels - 1, -1, -1):
            s = p.ratio ** k
            size = (max(2, round(w0 * s)), max(2, round(h0 * s)))
            if k:
                sigma = (1 / p.ratio - 1) * k
                a = cv2.resize(cv2.GaussianBlur(g0, (0, 0), sigma), size, interpolation=cv2.INTER_LINEAR)
                b = cv2.resize(cv2.GaussianBlur(g1, (0, 0), sigma), size, interpolation=cv2.INTER_LINEAR)
            else:
                a, b = g0, g1
            if flow is None:
                flow = np.zeros((size[1], size[0], 2), np.float32)
            else:
                flow = cv2.resize(flow, size, interpolation=cv2.INTER_LINEAR) / p.ratio
            flow = vr.calc(a, b, flow)
        return _finish(flow)


BACKENDS = (LiuFlow, DISFlow, TVL1Flow, DeepFlow, FarnebackFlow, VariationalRefinementFlow)


@hookimpl
def persona_register_backends(register):
    for cls in BACKENDS:
        register(cls)
