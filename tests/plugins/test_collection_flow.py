"""Collection flow (ALGORITHMS §7.2) against a known warp: it samples the photo through the
frontalizing map it is given (the frontalize backend's), bent by the TPS of the fiducials."""

import numpy as np

from persona.plugins.face.collection_flow import collection_flow
from persona.plugins.face.template import IDX49, generic_template
from persona.plugins.manager import default_registry


def _face(h, w):
    """A smooth, textured face-like image (H, W, 3) uint8: blobs of colour no flow can confuse."""
    ys, xs = np.mgrid[0:h, 0:w]
    rgb = [120 + 60 * np.sin(xs / 9.0 + c) * np.cos(ys / 11.0 - c) for c in (0.0, 1.0, 2.0)]
    return np.clip(np.stack(rgb, axis=-1), 0, 255).astype(np.uint8)


def test_the_photo_is_read_through_the_map_it_is_given():
    """A photo that is the canonical face moved by (7, 5) px, with a map that says so, comes back
    aligned (within 3 grey levels inside) by that map, the dense flow adding next to nothing."""
    template = generic_template()
    h, w = template.depth.shape
    canonical = _face(h, w)
    shift = np.float32([7, 5])
    photo = np.zeros((h + 10, w + 10, 3), np.uint8)
    photo[5:5 + h, 7:7 + w] = canonical  # canonical (x, y) is at photo (x + 7, y + 5)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    to_photo = np.stack([xs, ys], axis=-1) + shift
    fiducials = template.landmarks3d[list(IDX49), :2].astype(np.float64)
    visible = np.ones((h, w), bool)
    basis = (canonical.astype(np.float64) / 255)[None]
    basis /= np.linalg.norm(basis)
    flow = default_registry().get("flow", "dis")({})
    out = collection_flow(photo, to_photo, fiducials, visible, fiducials, basis, 10.0, flow)
    inside = out["collection/mask"].copy()
    inside[:12], inside[-12:], inside[:, :12], inside[:, -12:] = False, False, False, False
    error = np.abs(out["collection/rgb"].astype(int) - canonical)[inside]
    assert inside.mean() > 0.6 and np.median(error) <= 3, (inside.mean(), np.median(error))
    moved = out["collection/map"][inside] - to_photo[inside]  # what the dense flow added to the map
    assert np.median(np.linalg.norm(moved, axis=-1)) <= 0.5  # nothing: the map it was given did the aligning
