"""The contract of each backend kind: the method a backend implements and what it returns.

Shapes use (row, col) for images and (x, y) pixel coordinates for points, with
the centre of pixel (row i, col j) at (x=j, y=i) as in OpenCV and dlib.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .base import Backend


@dataclass(frozen=True)
class Landmarks:
    """The subject's face in one image.

    points : ndarray, shape (68, 2), float64 — iBUG 68 landmarks (x, y)
    box : ndarray, shape (4,), float64 — face box (left, top, right, bottom)
    n_faces : int — faces found in the image (the subject is one of them)
    """

    points: np.ndarray
    box: np.ndarray
    n_faces: int


@dataclass(frozen=True)
class Pose:
    """Head pose: canonical template point X maps to camera point ``R(rvec) X + tvec``.

    rvec, tvec : ndarray, shape (3,) — OpenCV Rodrigues rotation and translation
    camera : ndarray, shape (3, 3) — intrinsics K
    rms : float — reprojection error of the landmarks, pixels
    """

    rvec: np.ndarray
    tvec: np.ndarray
    camera: np.ndarray
    rms: float

    def as_vector(self) -> np.ndarray:
        """(rx, ry, rz, tx, ty, tz, f, cx, cy, rms) as float64, the store's row."""
        k = self.camera
        return np.r_[self.rvec, self.tvec, k[0, 0], k[0, 2], k[1, 2], self.rms].astype(np.float64)

    @classmethod
    def from_vector(cls, v: np.ndarray) -> "Pose":
        v = np.asarray(v, dtype=np.float64)
        camera = np.array([[v[6], 0, v[7]], [0, v[6], v[8]], [0, 0, 1.0]])
        return cls(v[0:3].copy(), v[3:6].copy(), camera, float(v[9]))


POSE_FIELDS = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "cx", "cy", "rms")


@dataclass(frozen=True)
class Frontal:
    """A face warped into the canonical frontal frame.

    rgb : ndarray, shape (H, W, 3), uint8
    mask : ndarray, shape (H, W), bool — canonical pixels seen in the photo (not self-occluded)
    landmarks : ndarray, shape (68, 2), float64 — the photo's landmarks in the canonical frame
    """

    rgb: np.ndarray
    mask: np.ndarray
    landmarks: np.ndarray


class LandmarkBackend(Backend):
    """Kind ``landmarks``: find the subject's face and its 68 landmarks."""

    kind = "landmarks"

    def detect(self, image: np.ndarray, hint: np.ndarray | None = None) -> Landmarks:
        """image: (h, w, 3) uint8 RGB; hint: (68, 2) landmarks from a sidecar file, or None."""
        raise NotImplementedError


class PoseBackend(Backend):
    """Kind ``pose``: head pose from the 68 landmarks."""

    kind = "pose"

    def estimate(self, landmarks: np.ndarray, image_size: tuple[int, int]) -> Pose:
        """landmarks: (68, 2); image_size: (height, width) of the photo."""
        raise NotImplementedError


class FrontalizeBackend(Backend):
    """Kind ``frontalize``: warp a posed face into the canonical frontal frame."""

    kind = "frontalize"

    def frontalize(self, image: np.ndarray, landmarks: np.ndarray, pose: Pose) -> Frontal:
        raise NotImplementedError

    def canonical_map(self, pose: Pose) -> np.ndarray:
        """(H, W, 2) float32: the photo's (x, y) seen by each canonical pixel at ``pose`` — the warp
        :meth:`frontalize` applies, which later stages (the collection flow) compose with theirs."""
        raise NotImplementedError


@dataclass(frozen=True)
class Puppet:
    """What a renderer knows of the puppet (actor B), in the canonical frame.

    appearance : ndarray, shape (H, W, 3), float32 — B's face for this frame, 0-255: its expression-dependent
        texture at the neutral fiducials (paper §5, video mode), or the static average
    coverage : ndarray, shape (H, W), float32 — fraction of photos that saw each pixel
    fiducials : ndarray, shape (49, 2) — B's neutral (mean) fiducials
    mesh : ndarray, shape (H, W, 3), float32, or None — B's face surface in this frame (paper §4:
        M_P^t, the average shape moved by the driver's adjusted motion): the canonical (x, y, Z) of
        the surface point that carries texture pixel (row v, col u) of ``appearance``, with the
        rigid head pose removed; NaN off the face. None when only a 2D puppet exists.
    mouth : ndarray, shape (rows, cols, 3), float32, or None — the inside of B's mouth from B's
        open-mouth photos (:mod:`persona.plugins.face.mouth`); None when no photo shows it
    lips : ndarray, shape (2, 5, 2), or None — B's neutral inner-lip curves (upper, lower; canonical
        x, y), where the mesh's lips are
    mouth_gap : float — how far apart the inner lips are in the photos ``mouth`` comes from (canonical
        px), or in the driver's frame (its px, with ``mouth_own``): the interior's own height (inf:
        unknown, the interior is stretched to any gap)
    mouth_own : bool — ``mouth`` is the driver's own, from this frame (``mouth_choice: frame``): sharp and
        already in the frame's light, its rows nearest the lips keep their size and the composite leaves
        it as it is (Rendered.own)
    lip_insets : ndarray, shape (2,), or None — where this frame's inner-lip corners lie, as fractions of
        the mouth's width in from its outer corners (:func:`persona.plugins.face.mouth.frame_insets`,
        from the driver's); None: where the mesh puts them
    jaw : ndarray, shape (17, 2), or None — B's jaw line (iBUG 0-16, canonical x, y), the median of B's
        aligned photos'; None when not known
    neutral : ndarray, shape (H, W, 3), or None — B's neutral texture, 0-255, on which the renderer judges
        where B's skin ends at the face's rim, the same in every frame; None: on ``appearance``
    """

    appearance: np.ndarray
    coverage: np.ndarray
    fiducials: np.ndarray
    mesh: np.ndarray | None = None
    mouth: np.ndarray | None = None
    lips: np.ndarray | None = None
    mouth_gap: float = np.inf
    mouth_own: bool = False
    lip_insets: np.ndarray | None = None
    jaw: np.ndarray | None = None
    neutral: np.ndarray | None = None


@dataclass(frozen=True)
class Rendered:
    """One output frame: rgb (h, w, 3) uint8, and mask (h, w) float32 in [0, 1], how much of each
    pixel is the face. rgb is the face's own colour wherever mask > 0, its soft edge included, not
    blended with anything (grey, 128, where mask is 0): the composite blends it into the driver's
    frame and ``puppet.mp4`` over grey (``persona.plugins.face.composite.alone``). Blended already,
    the soft edge would carry grey into the composite as a pale ring. ``own`` (h, w) float32 in [0, 1],
    or None: how much of each pixel shows the driver's own frame (its mouth interior, Puppet.mouth_own),
    already in the frame's light, which the composite does not relight."""

    rgb: np.ndarray
    mask: np.ndarray
    own: np.ndarray | None = None


class RenderBackend(Backend):
    """Kind ``render``: the puppet performing one driver frame."""

    kind = "render"
    #: True for renderers of the 3D puppet: the run then computes the driver's 3D motion and its
    #: transfer to the puppet, and ``puppet.mesh`` holds B's mesh of the frame
    uses_mesh: ClassVar[bool] = False

    def render(self, puppet: Puppet, target: np.ndarray, pose: Pose, frame: np.ndarray) -> Rendered:
        """target: (49, 2) canonical fiducials to show; pose: the driver's head pose in this
        frame; frame: the driver's frame (h, w, 3) uint8 (its size, and a background)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Shape:
    """The average shape of a collection, in the canonical frame (ALGORITHMS §8).

    normals : ndarray, shape (H, W, 3), float64 — unit normals ``(Z_x, Z_y, -1)/|.|`` (n_z < 0), NaN off the mask
    albedo : ndarray, shape (H, W), float64 — grey albedo ρ, NaN off the mask
    lighting : ndarray, shape (n, 4), float64 — per-image first-order SH light ``(l0, lx, ly, lz)``:
        image i ≈ ρ (l0 + l·n)
    depth : ndarray, shape (H, W), float64, or None — Z in canonical px (NaN off the mask); None when
        the backend leaves the integration to an ``integrate`` backend
    """

    normals: np.ndarray
    albedo: np.ndarray
    lighting: np.ndarray
    depth: np.ndarray | None = None


class ShapeBackend(Backend):
    """Kind ``shape``: photometric stereo over an aligned collection (ALGORITHMS §8)."""

    kind = "shape"

    def reconstruct(self, images: np.ndarray, mask: np.ndarray, visibility: np.ndarray | None,
                    template_normals: np.ndarray, template_depth: np.ndarray) -> Shape:
        """images: (n, H, W) grey or (n, H, W, 3) RGB float in [0, 1], aligned to the canonical frame;
        mask: (H, W) bool; visibility: (n, H, W) bool (False = pixel not seen) or None;
        template_normals: (H, W, 3); template_depth: (H, W)."""
        raise NotImplementedError

    def reconstruct_chunks(self, chunks, mask: np.ndarray, template_normals: np.ndarray,
                           template_depth: np.ndarray) -> Shape:
        """:meth:`reconstruct` of the images that ``chunks`` gives, an iterable (read once) of (images,
        visibility) pairs of consecutive images, each as :meth:`reconstruct` takes them. The DAG calls this,
        a shard of photos at a time; a backend that streams keeps its memory flat in the photos, and this
        default gathers them all and calls :meth:`reconstruct`."""
        pairs = list(chunks)
        images = np.concatenate([i for i, _ in pairs]) if pairs else np.empty((0, *np.shape(mask)))
        seen = None if all(v is None for _, v in pairs) else np.concatenate(
            [np.ones(np.shape(i)[:3], bool) if v is None else np.asarray(v) for i, v in pairs])
        return self.reconstruct(images, mask, seen, template_normals, template_depth)

    def images_for(self, n: int) -> np.ndarray:
        """Which of a collection's n aligned photos :meth:`reconstruct` is given (ascending
        indices): all of them unless a backend says otherwise."""
        return np.arange(n)


class IntegrateBackend(Backend):
    """Kind ``integrate``: depth from a normal field (ALGORITHMS §8.3)."""

    kind = "integrate"

    def integrate(self, normals: np.ndarray, mask: np.ndarray, *, reference: np.ndarray | None = None) -> np.ndarray:
        """normals: (H, W, 3) ``(Z_x, Z_y, -1)/|.|``; mask: (H, W) bool -> depth Z (H, W) float64,
        NaN off the mask. The free offset of each connected part of the mask is set so that its
        mean equals that of ``reference`` (H, W) there, or 0 when ``reference`` is None."""
        raise NotImplementedError


class FlowBackend(Backend):
    """Kind ``flow``: dense optical flow between two images (ALGORITHMS §6)."""

    kind = "flow"

    def flow(self, image0: np.ndarray, image1: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """image0, image1: (H, W) or (H, W, 3), float32/float64 in [0, 1] (uint8 accepted and
        scaled); mask: optional (H, W) bool of image0's pixels that matter (outside it the images
        are filled so that the flow does not latch onto the mask edge, ALGORITHMS §6.5).

        Returns w: (H, W, 2) float32, channels (dx, dy), on image0's grid, with
        ``image0(x) ≈ image1(x + w(x))``, the OpenCV / Ce Liu convention (ALGORITHMS §0).
        Mismatched or malformed inputs raise ValueError."""
        raise NotImplementedError


class DenoiseBackend(Backend):
    """Kind ``denoise``: edge-preserving denoising of a scalar field (ALGORITHMS §11), e.g. the
    magnitude f of the deformation transfer (ALGORITHMS §10, paper Sec. 4)."""

    kind = "denoise"

    def denoise(self, f: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """f: (H, W) float, in the units the backend's parameters assume (canonical px for the
        transfer magnitude); mask: (H, W) bool of the pixels whose value is data, or None for all.
        Pixels off the mask, and non-finite values of f, carry no data: the backend fills them
        from their neighbours (inpainting) or returns them as given (``none``).

        Returns u: (H, W) float64. Malformed inputs raise ValueError (TypeError for a non-bool mask)."""
        raise NotImplementedError


@dataclass(frozen=True)
class TexturePhotos:
    """The puppet's photo collection as texture synthesis sees it, in the canonical frame.

    photos : sequence of n raw photos (h_i, w_i, 3) uint8 — sampled once, through composed maps
    maps : ndarray, shape (n, H, W, 2), float32 — canonical pixel -> photo (x, y) (frontalizing map)
    visible : ndarray, shape (n, H, W), bool — canonical pixels each photo sees
    fiducials : ndarray, shape (n, 49, 2) — each photo's pose-corrected fiducials F^i
    """

    photos: tuple
    maps: np.ndarray
    visible: np.ndarray
    fiducials: np.ndarray

    def __len__(self) -> int:
        return len(self.photos)


@dataclass(frozen=True)
class Texture:
    """A synthesized face texture: rgb (H, W, 3) float32 in [0, 255]; mask (H, W) bool where
    any photo contributed."""

    rgb: np.ndarray
    mask: np.ndarray


class TextureBackend(Backend):
    """Kind ``texture``: the puppet's face with a target expression (paper §5, ALGORITHMS §12)."""

    kind = "texture"

    def synthesize(self, photos: TexturePhotos, target: np.ndarray, flow: FlowBackend | None = None,
                   reference: np.ndarray | None = None) -> Texture:
        """target: (49, 2) canonical fiducials F^T of the expression to show; flow: the backend
        of the dense warps (None: the one the backend's params name); reference: the frontalized
        reference photo (H, W, 3) whose expression F^T is (the paper's reference mode, Fig. 5),
        or None."""
        raise NotImplementedError

    # Video mode (optional; the paper's puppetry mode): the collection is aligned once, to its
    # mean fiducials, and only the expression weights change per frame. A backend without it
    # raises NotImplementedError and the run shows the static average instead.

    #: Video mode: the names of the params that act only where a frame's texture is blended from
    #: the cache (:meth:`expression`, :meth:`finish`), never on the cache itself (:meth:`cache`
    #: and the alignment before it). The stored cache is keyed by the other params alone, so a
    #: change of one of these recomputes the textures from the cache already stored. A backend
    #: that names none keys its cache on every param.
    frame_params: ClassVar[frozenset[str]] = frozenset()

    def cache(self, aligned):
        """The target-independent state of an aligned collection (``.rgb`` (n, H, W, 3) float
        0-255, ``.valid`` (n, H, W) bool), e.g. its pyramids."""
        raise NotImplementedError

    def blend(self, cache, fiducials: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The texture (H, W, 3) float32 for target fiducials (49, 2) from a :meth:`cache` of photos
        whose fiducials are ``fiducials`` (n, 49, 2)."""
        raise NotImplementedError

    # A drive reads the stored cache a shard of photos at a time: the blend of Eq. 3 as weights per
    # photo (weights), sums over the shards (persona.plugins.face.blend.BlendSums) and a last step.
    def weights(self, fiducials: np.ndarray, targets: np.ndarray, keep: slice = slice(None),
                neutral: np.ndarray | None = None, gazes: np.ndarray | None = None) -> np.ndarray:
        """The weights (m, n) of the photos (fiducials (n, 49, 2)) for the targets ``keep`` of
        consecutive frames' targets (T, 49, 2): a row per target kept, then any further rows that
        :meth:`finish` uses. ``neutral`` (49, 2): B's neutral fiducials in this drive (the ones its
        targets were retargeted about), for rows that stand for B at rest; None = the photos' mean.
        ``gazes`` (n, 2): where each photo looks (persona.plugins.face.gaze.photo_gazes; NaN where its
        irises were not found), for a backend that weighs the photos' eyes by it; None: not known."""
        raise NotImplementedError

    def finish(self, sums, totals, fiducials: np.ndarray, targets: np.ndarray, *,
               gaze: np.ndarray | None = None) -> np.ndarray:
        """The textures (f, H, W, 3) float32 from the sums over every photo of its :meth:`weights`; ``gaze``
        (f, 2, 2), where the driver looks in each frame (persona.plugins.face.gaze.gaze_shift), for a
        backend that moves the irises."""
        raise NotImplementedError


class LightBackend(Backend):
    """Kind ``light``: the light B's face takes in each frame of a drive, from A's light at B's edge as the
    render found it in each frame alone (docs/composite.md).

    The render fits, on each frame, A's light at the edge of B's face
    (:func:`persona.plugins.face.composite.light_plane`): a plane per colour channel of the log gain that
    takes B's render to A's frame there. A light backend turns those fits into the planes the composite
    applies, e.g. steady in time, so that hair or glasses passing under B's edge do not flicker B's face."""

    kind = "light"

    def light(self, planes: np.ndarray) -> np.ndarray:
        """planes: (T, 4, 3) float, one per frame of the drive in order, columns the R, G, B channels: the log
        gain's value at the top left corner of the mask's bounding box, its change across the box's width and
        down its height, and its mean along the edge it was fitted on; all NaN for a frame with no fit (no
        face, nothing like skin under B's edge).

        Returns (T, 4, 3) float64 in the same units: the planes each frame's composite applies (NaN: the
        frame's face keeps its own light). Malformed inputs raise ValueError."""
        raise NotImplementedError


class CompositeBackend(Backend):
    """Kind ``composite``: B's rendered face blended into one of A's frames (``composite.mp4``'s frames)."""

    kind = "composite"

    def composite(self, face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, plane: np.ndarray,
                  own: np.ndarray | None = None, points: np.ndarray | None = None) -> np.ndarray:
        """face: (h, w, 3) uint8, B's render, its own colour across its soft edge (:class:`Rendered`);
        frame: (h, w, 3) uint8, A's frame; alpha: (h, w) float32 in [0, 1], the render's mask; plane:
        (4, 3), the light B's face takes in this frame (a :class:`LightBackend`'s; all NaN: none); own:
        (h, w) float32 in [0, 1], the share of each pixel that is A's own already (Rendered.own, e.g. A's
        mouth interior drawn into B's gap), or None; points: A's 68 landmarks (68, 2) in the frame (x, y
        px), or None.

        Returns the composite (h, w, 3) uint8: A's frame where alpha is 0."""
        raise NotImplementedError


@dataclass(frozen=True)
class MouthPhotos:
    """B's accepted photos as the mouth interior sees them, in the order of the collection.

    photos : sequence of n photos (h_i, w_i, 3) uint8, each read from the store when indexed (a backend
        reads only those it uses)
    points : ndarray, shape (n, 68, 2), float64 — each photo's iBUG 68 landmarks (x, y, the photo's px)
    landmarks : ndarray, shape (n, 68, 2), float64 — the same landmarks in the canonical frame
    """

    photos: Sequence
    points: np.ndarray
    landmarks: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class MouthInterior:
    """One image of the inside of B's mouth.

    image : ndarray, shape (rows, cols, 3), uint8 — the interior between the inner lips, unrolled: rows run
        from the upper inner lip down to the lower, columns along the mouth from inner corner iBUG 60 to 64
        (:mod:`persona.plugins.face.mouth`; the renderer maps it into the gap between B's lips in each frame)
    gap : float — how far apart the inner lips are in the photos it comes from (canonical px): the interior's
        own height
    """

    image: np.ndarray
    gap: float


@dataclass(frozen=True)
class Mouth:
    """What a mouth backend makes of B's photos.

    interior : MouthInterior, or None — the inside of B's mouth the renderer draws (None: no photo shows it, the
        mouth opens onto nothing)
    cavity : MouthInterior, or None — with ``choice`` ``driver``, B's mouth as it shows no teeth (the darkest),
        which each frame takes as the driver's own mouth shows no teeth (:meth:`MouthBackend.teeth`); None otherwise
    lips : ndarray, shape (2, 5, 2), float64 — B's neutral inner-lip curves (upper, lower; canonical x, y), where
        the mesh's lips are
    """

    interior: MouthInterior | None
    cavity: MouthInterior | None
    lips: np.ndarray


class MouthBackend(Backend):
    """Kind ``mouth``: the inside of B's mouth (teeth, tongue, cavity) that a renderer of the 3D puppet draws
    where B's lips part, and how much of B's teeth each frame of a drive shows.

    A mesh made from photos has no inside: where the driver opens its mouth, B's lips part over nothing. The
    render's params say how it is chosen (``stages.render.params``: ``mouth_photos``, ``mouth_min_gap``,
    ``mouth_choice``, ``mouth_sigma``), and a mouth backend follows them; its own params are
    ``stages.mouth.params``."""

    kind = "mouth"

    def interior(self, photos: MouthPhotos, *, count: int, min_gap: float, choice: str) -> Mouth:
        """photos: B's accepted photos; count: how many photos one interior is made of (at most); min_gap: how far
        apart (inter-ocular distances) a photo's inner lips must be for it to show the interior; choice:
        ``widest`` (the photos whose lips are furthest apart), ``darkest`` (those darkest between the lips, an
        open mouth without teeth) or ``driver`` (both: the widest as ``interior``, the darkest as ``cavity``).
        Malformed inputs raise ValueError."""
        raise NotImplementedError

    def teeth(self, frames: Iterable[tuple[np.ndarray, np.ndarray]], sigma: float) -> np.ndarray:
        """frames: each frame of the drive in order, (its image (h, w, 3) uint8, the driver's 68 landmarks in it
        (68, 2), NaN in a frame without a face); sigma: how steady in time (frames) the result is.

        Returns (T,) float in [0, 1]: how much of B's teeth (1) rather than B's cavity (0) the mouth shows in
        each frame, as the driver's own mouth shows them there. Called only with ``choice`` ``driver`` and both
        interiors made; otherwise every frame takes 1."""
        raise NotImplementedError


@dataclass(frozen=True)
class MotionPair:
    """What a motion transfer is set up from, once per drive; every array in the canonical frame (px), meshes as
    the canonical (x, y, Z) of the surface point that carries each texture pixel, Z in canonical px.

    driver_mean : ndarray, shape (H, W, 3) — M̄_D, the driver's mean mesh over the drive
    correspondence : ndarray, shape (H, W, 2) — φ: for each pixel of B's face, the (x, y) of A's face it stands for
    puppet : ndarray, shape (H, W, 3) — M_P, B's average mesh
    puppet_mask, driver_mask : ndarray, shape (H, W), bool — B's face, A's face
    fiducials : ndarray, shape (49, 2) — B's mean fiducials (x, y)
    targets : ndarray, shape (T, 49, 2) — B's target fiducials in each frame of the drive (the retarget's)
    denoiser : DenoiseBackend, or None — the workflow's ``stages.denoise`` when it names one (None: the
        backend's own choice)
    """

    driver_mean: np.ndarray
    correspondence: np.ndarray
    puppet: np.ndarray
    puppet_mask: np.ndarray
    driver_mask: np.ndarray
    fiducials: np.ndarray
    targets: np.ndarray
    denoiser: DenoiseBackend | None = None


class TransferBackend(Backend):
    """Kind ``transfer``: the driver's motion carried onto B's face (paper §4: deformation transfer), the
    meshes a renderer of the 3D puppet draws. A's meshes move with A's face; the transfer says how the same
    expression moves B's, whose face has another shape."""

    kind = "transfer"

    def prepare(self, pair: MotionPair) -> Callable[[int, np.ndarray], np.ndarray]:
        """Set up once per drive (each worker calls it once and keeps the result for its frames).

        Returns a function (t, driver_mesh) -> B's mesh of frame t: driver_mesh (H, W, 3) float32 is M_D^t, A's
        mesh of frame t; the result (H, W, 3) float is M_P^t, in the units of ``pair.puppet``. Values off
        ``pair.puppet_mask`` are not kept (the store holds NaN there)."""
        raise NotImplementedError
