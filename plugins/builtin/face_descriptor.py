"""dlib's 128-D face descriptor network, read from its model file and run in NumPy.

The identity figures of ``persona evaluate`` describe a few hundred faces a drive with dlib's ResNet
(``dlib_face_recognition_resnet_model_v1.dat`` in ``face_recognition_models``: 29 convolutions, about
0.27 G multiply-adds a face). The dlib wheel runs it on its own matrix code, about 100 ms a face on one
core here; the same weights through NumPy's BLAS give the same descriptor (within 1e-6) in about a
fifth of that. dlib still cuts the 150 x 150 face chip (``dlib.get_face_chip``); this module does the
rest.

The network (dlib's ``dnn_face_recognition_ex``), from its input:

- the chip less the mean colour (122.782, 117.001, 104.298), over 256;
- a 7 x 7 convolution of 32 filters at stride 2, an affine (the batch norm, folded), ReLU, and a 3 x 3
  max pool at stride 2;
- residual blocks of two 3 x 3 convolutions (each followed by an affine, the first by a ReLU), added to
  the block's input and passed through a ReLU: 3 of 32 filters, 4 of 64, 3 of 128, 3 of 256 and one more
  of 256. The first block of each width after the first starts at stride 2, and its input, averaged
  over 2 x 2 at stride 2, is added with zeros where the two differ in channels or size (dlib's
  ``add_prev``);
- the mean over the remaining positions, and a 256 x 128 linear map without bias: the descriptor.

Convolutions at stride 1 pad by one; at stride 2, and the pools, do not pad (dlib's defaults).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: dlib's input layer subtracts this mean colour (R, G, B) and divides by 256
MEAN_RGB = np.float32([122.782, 117.001, 104.298])

#: the number of filters of each convolution, in order from the input (the 7 x 7 one first)
WIDTHS = (32,) + (32,) * 6 + (64,) * 8 + (128,) * 6 + (256,) * 6 + (256,) * 2


@dataclass(frozen=True)
class Conv:
    """A convolution as one matrix product: ``weights`` (size * size * channels in, filters), channels last."""

    weights: np.ndarray
    bias: np.ndarray
    size: int
    stride: int
    pad: int


@dataclass(frozen=True)
class Network:
    """The weights of dlib's face descriptor network, in order from the input."""

    convs: tuple[Conv, ...]
    affines: tuple[tuple[np.ndarray, np.ndarray], ...]  # (scale, shift) after each convolution
    linear: np.ndarray  # (256, 128)


def _int(blob: bytes, at: int) -> tuple[int, int]:
    """One integer of dlib's serialisation: a byte of its length (and 0x80 for a negative), then its bytes,
    least significant first."""
    head = blob[at]
    value = int.from_bytes(blob[at + 1:at + 1 + (head & 0x0F)], "little")
    return (-value if head & 0x80 else value), at + 1 + (head & 0x0F)


def _tensor(blob: bytes, at: int) -> tuple[np.ndarray, int]:
    """One tensor of dlib's serialisation: version 2, four dimensions, then little-endian float32s."""
    version, at = _int(blob, at)
    if version != 2:
        raise ValueError(f"a tensor of version {version}, not 2")
    dims = []
    for _ in range(4):
        d, at = _int(blob, at)
        dims.append(d)
    n = int(np.prod(dims))
    return np.frombuffer(blob, "<f4", n, at).reshape(dims), at + 4 * n


def read_network(path: str) -> Network:
    """The network's weights from dlib's model file at ``path``. Each convolution (``con_4``), affine
    (``affine_``) and the final linear map (``fc_2``) is found by its serialised name and read; a file of
    another network (other widths, strides or order) raises ValueError."""
    with open(path, "rb") as f:
        blob = f.read()
    convs, affines, linear = [], [], None
    for found in re.finditer(rb"\x01\x05con_4|\x01\x07affine_|\x01\x04fc_2", blob):
        name, at = found.group()[2:], found.end()
        if name == b"con_4":
            params, at = _tensor(blob, at)
            fields = []
            for _ in range(7):  # filters, rows, columns, stride y and x, padding y and x
                value, at = _int(blob, at)
                fields.append(value)
            filters, rows, cols, stride, _, pad, _ = fields
            params = params.ravel()
            channels = (params.size - filters) // (filters * rows * cols)
            kernel = params[:filters * channels * rows * cols].reshape(filters, channels, rows, cols)
            convs.append(Conv(np.ascontiguousarray(kernel.transpose(2, 3, 1, 0).reshape(-1, filters)),
                              params[-filters:].copy(), rows, stride, pad))
        elif name == b"affine_":
            params, at = _tensor(blob, at)
            params = params.ravel()
            affines.append((params[:params.size // 2].copy(), params[params.size // 2:].copy()))
        else:
            outputs, at = _int(blob, at)
            inputs, at = _int(blob, at)
            params, at = _tensor(blob, at)
            linear = params.reshape(inputs, outputs).copy()
    widths = tuple(c.bias.size for c in convs)
    if widths != WIDTHS or len(affines) != len(convs) or linear is None or linear.shape != (256, 128):
        raise ValueError(f"{path}: not dlib's face descriptor network (convolution widths {widths}, "
                         f"{len(affines)} affine layers, linear map {None if linear is None else linear.shape})")
    return Network(tuple(convs), tuple(affines), linear)


@lru_cache(maxsize=1)
def network() -> Network:
    """The network of ``face_recognition_models``' descriptor model, read once per process."""
    import face_recognition_models

    return read_network(face_recognition_models.face_recognition_model_location())


def _reach(size: int, offset: int, stride: int, out: int) -> tuple[int, int, int]:
    """Along one axis of a window's pixel ``offset`` (its place in the window less the padding): the
    first and last + 1 outputs whose pixel lies inside the input's ``size``, and the first such pixel."""
    first = max(0, -(offset // stride))  # ceil(-offset / stride)
    last = min(out, (size - 1 - offset) // stride + 1)
    return first, last, first * stride + offset


def _convolve(x: np.ndarray, conv: Conv) -> np.ndarray:
    """(h, w, channels) float32 -> (h', w', filters): every window's pixels side by side, times the weights.
    The zero padding is the windows' own zeros, not a padded copy of ``x``."""
    h, w, channels = x.shape
    n, s, p = conv.size, conv.stride, conv.pad
    oh, ow = (h + 2 * p - n) // s + 1, (w + 2 * p - n) // s + 1
    windows = (np.zeros if p else np.empty)((oh, ow, n, n, channels), np.float32)
    for dy in range(n):
        i0, i1, y0 = _reach(h, dy - p, s, oh)
        for dx in range(n):
            j0, j1, x0 = _reach(w, dx - p, s, ow)
            windows[i0:i1, j0:j1, dy, dx] = x[y0:y0 + s * (i1 - i0 - 1) + 1:s, x0:x0 + s * (j1 - j0 - 1) + 1:s]
    return (windows.reshape(oh * ow, -1) @ conv.weights + conv.bias).reshape(oh, ow, -1)


def _pool(x: np.ndarray, size: int, reduce) -> np.ndarray:
    """``reduce`` (np.max or np.mean) over size x size windows at stride 2, without padding."""
    h, w, _ = x.shape
    oh, ow = (h - size) // 2 + 1, (w - size) // 2 + 1
    return reduce(np.stack([x[dy:dy + 2 * (oh - 1) + 1:2, dx:dx + 2 * (ow - 1) + 1:2]
                            for dy in range(size) for dx in range(size)]), axis=0)


def _add(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a + b, each extended with zeros to the larger of their sizes along every axis (dlib's add_prev)."""
    out = np.zeros(np.maximum(a.shape, b.shape), np.float32)
    out[:a.shape[0], :a.shape[1], :a.shape[2]] += a
    out[:b.shape[0], :b.shape[1], :b.shape[2]] += b
    return out


def describe_chip(chip: np.ndarray, net: Network | None = None) -> np.ndarray:
    """The 128-D descriptor (float32) of a face chip: (150, 150, 3) uint8 RGB, as ``dlib.get_face_chip``
    cuts it."""
    net = network() if net is None else net
    if chip.shape != (150, 150, 3):
        raise ValueError(f"face descriptor: want a (150, 150, 3) chip, got {chip.shape}")

    def layer(x, i, relu):
        scale, shift = net.affines[i]
        y = _convolve(x, net.convs[i]) * scale + shift
        return np.maximum(y, 0, out=y) if relu else y

    x = layer((np.asarray(chip, np.float32) - MEAN_RGB) / 256, 0, relu=True)
    x = _pool(x, 3, np.max)
    for i in range(1, len(net.convs), 2):
        branch = layer(layer(x, i, relu=True), i + 1, relu=False)
        x = _add(branch, _pool(x, 2, np.mean)) if net.convs[i].stride == 2 else x + branch
        x = np.maximum(x, 0, out=x)
    return x.mean(axis=(0, 1)) @ net.linear
