"""Kind ``texture``: the puppet's face with a target expression (paper §5 and its Fig. 5 baselines).

* ``multiscale`` (the paper, the default): every photo TPS- and flow-aligned to the target, then
  the Laplacian-pyramid weighted average of Eq. 3: coarse levels from all photos (one consistent
  colour), fine levels from the photos whose expression is nearest the target (sharp, the
  person's own creases). The maths is in :mod:`persona.plugins.face.blend`.
* ``static`` (baseline ii): one static average of the aligned collection, TPS-warped to the target.
* ``weighted`` (baseline iii): the expression-weighted average of the rigidly frontalized photos.
* ``prewarped`` (baseline iv): that average after the TPS and dense pre-warping, at a single scale.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from ..base import Params
from ..face import brows, eyes, texture as align
from ..face.gaze import ahead, look, together
from ..face.blend import BlendCache, BlendSums, BlendTotals, chosen, expression_weights
from ..face.dynamics import smooth_in_time, time_radius
from ..face.fiducials import gap_square_distance, mean_shape
from ..face.template import CANONICAL_HEIGHT as H, CANONICAL_WIDTH as W
from ..face.warp import FACING, tps_map
from ..hookspecs import hookimpl
from ..kinds import Texture, TextureBackend
from ..manager import FlowChoice


#: texels above and below a part's region (the eyes', the brows') over which its own rows are summed too
#: (MultiscaleTexture.sums), for what the pyramid's collapse carries into the region: with none the eyes are
#: up to 0.11 grey levels off the whole image's sums, with 4 0.002, with 8 or more exactly the same
#: (tests/plugins/test_texture.py, random photos)
REGION_MARGIN = 12

#: where in a texture at the fiducials ``neutral`` each part blended with its own weights shows: (neutral,
#: shape) -> (H, W) weights in [0, 1]
REGIONS = {"eyes": eyes.region, "brows": brows.region}


class _Weights(Params):
    sigma: float = Field(10.0, gt=0, description="σ of the expression weight e_i = exp(-||F^T - F^i||² / 2σ²), "
                         "canonical px over the 49 fiducials (paper: 10)")
    min_share: float = Field(0.16, ge=0, le=1, description="σ widened, for a target few of B's photos are near "
                             "(an expression B rarely makes), until its weights draw on this share of them, "
                             "(Σe)²/Σe² (persona.plugins.face.blend.widened). Not in the paper, whose §8 widens "
                             "σ for a whole collection that is small (0: σ as given). 0.16 draws the rarest "
                             "frames of the woman's drives on 38 photos where 5 drew them, with their streaks "
                             "and glasses (docs/texture.md)")

    eye_sigma: float = Field(1.0, ge=0, description="σ (canonical px) of the eyes' own expression weight, over "
                             "how far apart their lids are (the four facing pairs' heights) rather than the 49 "
                             "fiducials; the eyes' region of the texture is blended with it, so B's eyes open "
                             "and narrow with the target's whatever its mouth does. Not in the paper (0: the "
                             "eyes take the face's weights, as there). σ is widened by `min_share` like the "
                             "face's. 1 raises Bush ← Obama's eye gain 0.56 → 0.62 (docs/expression.md)")

    brow_sigma: float = Field(3.0, ge=0, description="σ (canonical px) of the brows' own expression weight, over "
                              "where each brow's points lie from its eye's middle rather than the 49 fiducials; the "
                              "region above the eyes (brows, forehead, the creases between the brows) is blended "
                              "with it, so its creases are those of photos whose brows do what the target's do, "
                              "whatever its mouth does (persona.plugins.face.brows). Not in the paper (0: the "
                              "face's weights, as there). σ is widened by `min_share` like the face's. 3 raises the "
                              "brow gain on 17 of the 20 example drives (Obama ← MEAD happy 0.82 -> 1.00; "
                              "docs/expression.md)")

    def weights_of(self, fiducials: np.ndarray, target: np.ndarray, *, relative: bool = True,
                   part: str = "face") -> np.ndarray:
        """e_i (n,) of photos with fiducials (n, 49, 2) for a target (49, 2): Eq. 3's, σ widened for a
        rare target (``min_share``); of ``part`` "eyes", the eyes' own (``eye_sigma``), of "brows" the
        brows' own (``brow_sigma``)."""
        sigma, distance = {"face": (self.sigma, None),
                           "eyes": (self.eye_sigma, lambda f, t: gap_square_distance(f, t, FACING[:4])),
                           "brows": (self.brow_sigma, brows.square_distance)}[part]
        return expression_weights(fiducials, target, sigma, relative=relative,
                                  min_photos=self.min_share * len(fiducials), distance=distance)

    @property
    def parts(self) -> list[str]:
        """The parts of the face blended with weights of their own, in the order they are laid over the face's
        blend: the brows (``brow_sigma``), then the eyes (``eye_sigma``); those whose σ is not 0."""
        return [part for part, sigma in (("brows", self.brow_sigma), ("eyes", self.eye_sigma)) if sigma > 0]


class _Alignment(_Weights):
    tps_lambda: float = Field(10.0, ge=0, description="λ of the smoothing thin-plate spline to the target "
                              "(paper Eq. 1: 10; s = 8πλ, ALGORITHMS §5.2)")
    rank: int = Field(4, ge=1, le=16, description="rank of the appearance subspace the dense flow aligns "
                      "each photo to (paper: 4, lighting only)")
    flow: FlowChoice = Field(default_factory=FlowChoice, description="the flow of the dense warps to a target "
                             "(per-target synthesis, `persona evaluate --texture` and, with video_alignment own, "
                             "the drive); varref rather than the collection flow's dis, as measured in "
                             "docs/texture.md")

    def aligned(self, photos, target, flow=None, reference=None) -> align.Aligned:
        """The photos TPS- and flow-aligned to the target, with ``flow`` or else this flow choice's."""
        return align.align(photos, target, flow or self.flow.build(), tps_lambda=self.tps_lambda, rank=self.rank,
                           reference=reference)

    # the same two steps for a collection held a shard at a time (the drive's cache)
    def warped(self, photos, target) -> tuple[align.Aligned, np.ndarray]:
        """Step 1 on some of the photos: TPS-warped to the target, and their maps."""
        return align.tps_aligned(photos, target, tps_lambda=self.tps_lambda)

    def flowed(self, photos, warped: align.Aligned, maps: np.ndarray, basis: np.ndarray) -> align.Aligned:
        """Step 2 on the same photos: flowed to their projections on the basis of all of them
        (align.warped_basis of every photo's step 1)."""
        return align.flow_aligned(photos, warped, maps, basis, self.flow.build())


def _weighted_mean(rgb: np.ndarray, weights: np.ndarray) -> Texture:
    """Σ_i w_i(x) rgb_i(x) / Σ_i w_i(x) with weights (n, H, W)."""
    total = weights.sum(axis=0)
    out = np.einsum("nhw,nhwc->hwc", weights, rgb) / np.where(total > 0, total, np.inf)[..., None]
    return Texture(out.astype(np.float32), total > 0)


def _expression_mean(aligned: align.Aligned, fiducials: np.ndarray, target: np.ndarray, params: _Weights) -> Texture:
    """The photos' average weighted by e_i (relative, so never all zero) where each one sees."""
    e = params.weights_of(fiducials, target)
    return _weighted_mean(aligned.rgb, e[:, None, None] * aligned.valid)


def alignment_confidence(aligned: align.Aligned, stretch_scale: float, residual_scale: float) -> np.ndarray | None:
    """Each photo's local alignment confidence (n, H, W) in [0, 1]: exp(-m / 2s²) of each misfit measure m of
    ``aligned`` (its stretch, its residual) whose scale s is not 0, multiplied; None when the alignment carries
    no misfit measures (video mode's collection flow) or both scales are 0."""
    out = None
    for misfit, scale in ((aligned.stretch, stretch_scale), (aligned.residual, residual_scale)):
        if misfit is not None and scale > 0:
            term = np.exp(-misfit / np.float32(2 * scale ** 2))
            out = term if out is None else out * term
    return out


def _eyes_moved(textures: np.ndarray, targets: np.ndarray, neutral: np.ndarray, p, gaze: np.ndarray | None,
                close_eyes: bool) -> np.ndarray:
    """The textures (f, H, W, 3) of the targets (f, 49, 2), whose geometry is B's ``neutral`` fiducials, in
    place: with ``gaze`` (f, 2, 2) and MultiscaleTexture's ``gaze`` in ``p``, the irises turned (gaze.look),
    both eyes by their mean with its ``gaze_together``; with ``close_eyes``, the eyes a target shuts drawn
    shut (eyes.lower, between its ``shut_from`` and ``shut_at``). The eyes turn first, so that a closing lid
    comes down over them."""
    if gaze is not None and p.gaze:
        for texture, shift in zip(textures, together(gaze) if p.gaze_together else gaze):
            texture[:] = look(texture, neutral, shift)
    if close_eyes:
        for texture, target in zip(textures, targets):
            visible = eyes.lowered(target, neutral, start=p.shut_from, end=p.shut_at)
            texture[:] = np.clip(eyes.lower(texture, neutral, visible, meet=p.shut_meet, fade=p.shut_fade), 0, 255)
    return textures


class _ClosingEyes(Params):
    """The eyes a target shuts, drawn shut in its texture (persona.plugins.face.eyes; video mode)."""

    close_eyes: bool = Field(True, description="when the target closes an eye (its lids less than "
                             "`shut_from` as far apart as at B's neutral), draw that eye's upper lid down over "
                             "it, to cover it all at `shut_at`: B's photos rarely show shut eyes, and a mesh "
                             "squeezes an open eye rather than covers it (persona.plugins.face.eyes). Not in the "
                             "paper")
    shut_from: float = Field(eyes.SHUT_FROM, gt=0, le=1, description="close_eyes: the lids' distance, over B's "
                             "neutral one, below which the upper lid starts to come down (the open-eye frames' 10th "
                             "percentile on the self-reenactment: 0.87). 0.9 rather than 0.85 brings the "
                             "self-reenactment's composite eye gain 0.92 -> 1.03 and Bush <- Obama's 0.69 -> "
                             "0.71 (docs/expression.md)")
    shut_at: float = Field(eyes.SHUT_AT, ge=0, lt=1, description="close_eyes: the distance at which it is fully "
                           "shut (dlib's lid points of a shut eye stay 25-50 % of their open distance apart, the "
                           "less the sharper the clip). 0.3 rather than 0.45 draws the HD drivers' half-shut eyes "
                           "half open, not as slits of lashes (docs/expression.md)")
    shut_meet: float = Field(eyes.SHUT_MEET, gt=0, le=1, description="close_eyes: how far down the eye's "
                             "opening the upper lid comes to shut it, its line of lashes there; the lower lid "
                             "rises the rest of the way. 1: the lashes on the lower lid's line, which left the "
                             "open eye's outline around them and read open; 0.6 took Bush <- Obama's eye gain "
                             "0.68 -> 0.72 (docs/expression.md)")
    shut_fade: float = Field(eyes.SHUT_FADE, ge=0, description="close_eyes: over how many texels of its travel "
                             "a lid and its line of lashes fade in (0: drawn in full as soon as the eye narrows "
                             "past `shut_from`, as before). A lid that has come down a fraction of a texel lies on "
                             "the texture's own lashes, and new ones drawn over them made a dark line of eyeliner "
                             "across an eye barely narrower than B's neutral (docs/expression.md)")

    @model_validator(mode="after")
    def _shut(self):
        if self.shut_at >= self.shut_from:
            raise ValueError(f"shut_at ({self.shut_at}) must be below shut_from ({self.shut_from})")
        return self


class MultiscaleTexture(TextureBackend):
    name = "multiscale"
    description = ("expression-dependent texture: photos aligned to the target (TPS + flow), blended in a "
                   "Laplacian pyramid with expression and detail weights (paper §5, Eq. 3)")
    default = True
    #: part of the texture stages' cache keys: raised whenever the same params give a different texture
    version = "13"
    #: what :meth:`weights` and :meth:`finish` read and :meth:`cache` does not (``tau`` is read by both)
    frame_params = frozenset({"sigma", "eye_sigma", "brow_sigma", "eye_gaze", "min_share", "skip", "time_sigma",
                              "detail_share", "finest_share", "detail_from", "close_eyes", "shut_from", "shut_at",
                              "shut_meet", "shut_fade", "gaze", "gaze_together"})

    class Params(_ClosingEyes, _Alignment):
        levels: int = Field(5, ge=2, le=8, description="pyramid levels p (the paper does not say; 5 gives a "
                            "16x13 coarsest level at 244x194, ALGORITHMS §16.5)")
        alpha: float = Field(1.0, ge=0, description="α: exponent of the detail (Laplacian) response in the "
                             "weight (paper: 1)")
        beta: float = Field(20.0, gt=0, description="β: fall-off of the uniform term τ l^-β with the level l "
                            "(paper: 20; l = 0, the coarsest, is uniform)")
        tau: float = Field(1.0, ge=0, description="τ: weight of the uniform term (paper: 1); 0 = none, so every "
                           "level follows the expression, the coarsest too (its colour then follows the photos "
                           "chosen)")
        detail_blur: float = Field(1.0, ge=0, description="σ (px) of the Gaussian blur before the Laplacian "
                                   "filter of the detail response L^i (the paper does not say)")
        detail_floor: float = Field(1e-6, gt=0, description="added to |Laplacian| so flat regions keep a weight")
        video_alignment: Literal["own", "collection"] = Field(
            "own", description="video mode (the drive): B's collection aligned to B's mean fiducials with this "
            "backend's own `flow`, and blended with the alignment confidence (own); or blended as the align "
            "stage's collection flow (stages.flow, dis) warped it, without a confidence (collection: a minute "
            "faster, but it tears tight low-resolution crops; docs/texture.md)")
        skip: float = Field(1e-6, ge=0, lt=1, description="photos with e_i below skip · max(e) are left out of "
                            "the fine levels' sums (their share there is below this); 0 keeps every photo")
        detail_share: float = Field(0.7, ge=0, le=1, description="ρ: the share of the fine energy the blend "
                                    "lost that is given back. A weighted mean of photos has less of the fine detail "
                                    "they do not share (skin, the exact place of a crease) than any one photo; each "
                                    "band but the two coarsest is scaled by one factor, the one that gives B's "
                                    "neutral blend e + ρ (E - e), e its energy and E one photo's. Not in the paper "
                                    "(0, with `finest_share` 0, is its blend). With `finest_share` 1 and "
                                    "`detail_from` neutral and the eyes' own weights and detail (`eye_sigma`), 0.7 "
                                    "keeps at least 0.6 of B's photos' detail on every cross-identity example "
                                    "workflow (0.65: 0.5995 on MEAD surprised); more costs dlib's readings of the "
                                    "face's features (docs/texture.md)")
        finest_share: float = Field(1.0, ge=0, le=1, description="ρ₀: the share given back at the pyramid's "
                                    "finest level, where the blend loses most (a photo has 3 times its energy) and "
                                    "which holds grain rather than the features dlib places points on. Not in the "
                                    "paper")
        detail_from: Literal["frame", "neutral"] = Field(
            "neutral", description="video mode: what `detail_share` gives back in each frame: more of the frame's "
            "own fine bands (frame), or of B's neutral blend's, the same in every frame (neutral), so that the "
            "detail given back holds still while the photos a frame takes change; the eyes' region, with "
            "`eye_sigma`, always takes its own. Not in the paper. At the defaults, neutral changes the texture "
            "from frame to frame less (docs/texture.md)")
        time_sigma: float = Field(0.0, ge=0, le=10, description="video mode: σ (frames) of a Gaussian over time "
                                  "taken of each photo's expression weight, so that the photos a frame's texture is "
                                  "made of change from frame to frame gradually rather than at once. Not in the "
                                  "paper (0, the default: each frame's own weights, the paper's); 1.5 halves the "
                                  "texture's change from frame to frame on the cross-identity drives, but lowers the "
                                  "self-reenactment's mouth gain, whose teeth come from the texture (docs/texture.md)")
        eye_gaze: float = Field(0.05, ge=0, le=1, description="video mode: σ (eye widths) of the eyes' weights "
                                "for where each photo's irises sit, from where B's photos usually have them: the eyes' "
                                "blend takes photos whose irises lie on one another (blended with those looking aside, "
                                "a doubled, grey iris), and `gaze` turns them. Not in the paper (0: off; docs/gaze.md)")
        gaze: bool = Field(True, description="video mode: B's eyes turn under their lids, the irises as far from "
                           "where they usually are as the driver's are from where the driver's usually are in the "
                           "clip, in eye widths (persona.plugins.face.gaze): the eyes look where the driver's look. "
                           "Not in the paper (false: B's irises stay where B's photos have them; docs/gaze.md)")
        gaze_together: bool = Field(False, description="gaze: true: both of B's eyes turn by the mean of the "
                                    "driver's two, never apart; false: each eye turns as the driver's same eye does "
                                    "where the clip's turn of one eye against the other stands out from its "
                                    "measure's noise, so eyes that converge on something near or cross do so on B's "
                                    "face too (persona.plugins.face.gaze.turns_apart; docs/gaze.md)")
        stretch_scale: float = Field(0.3, ge=0, description="s of the alignment confidence's flow term "
                                     "exp(-|∇w_i|² / 2s²), |∇w_i|² the local (σ 3 px) squared Jacobian norm of "
                                     "the photo's dense flow: tears, where the flow jumps, lose their weight. "
                                     "Not in the paper (0 turns it off; chosen as the README's texture section says)")
        residual_scale: float = Field(0.02, ge=0, description="s of the alignment confidence's residual term "
                                      "exp(-r² / 2s²), r² the local (σ 3 px) squared difference of the band-passed "
                                      "grey (0-1) aligned photo and its rank-k projection: where the flow left a "
                                      "feature off the target's place. Not in the paper (0 turns it off); 0.02 "
                                      "chosen with stretch_scale")

    def confidence(self, aligned: align.Aligned) -> np.ndarray | None:
        """Each photo's local alignment confidence (:func:`alignment_confidence`) at the params' scales."""
        return alignment_confidence(aligned, self.params.stretch_scale, self.params.residual_scale)

    def cache(self, aligned: align.Aligned, fill: np.ndarray | None = None) -> BlendCache:
        """The target-independent terms of Eq. 3 for an aligned collection (video mode), or for a
        shard of it with the collection's ``fill`` (BlendCache.build)."""
        p = self.params
        return BlendCache.build(aligned.rgb, aligned.valid, levels=p.levels, alpha=p.alpha, beta=p.beta,
                                tau=p.tau, blur=p.detail_blur, floor=p.detail_floor,
                                confidence=self.confidence(aligned), fill=fill)

    @property
    def time_radius(self) -> int:
        """Video mode: how many frames on each side a frame's expression weights take in (``time_sigma``)."""
        return time_radius(self.params.time_sigma)

    def expression(self, fiducials: np.ndarray, targets: np.ndarray, keep: slice = slice(None), *,
                   part: str = "face") -> np.ndarray:
        """Video mode: the expression weights (f, n) of the targets ``keep`` of consecutive frames' targets
        (T, 49, 2), over photos whose fiducials are (n, 49, 2): each photo's weight Gaussian-averaged over
        the frames around (``time_sigma``; the targets should reach :attr:`time_radius` frames beyond
        ``keep`` where the video does), those below ``skip`` of a frame's largest then set to 0
        (blend.chosen); of a ``part``, its own weights (``_Weights.weights_of``)."""
        p = self.params
        # without a uniform term only the ratios of the e_i matter: relative ones cannot all underflow
        e = np.stack([p.weights_of(fiducials, t, relative=p.tau == 0, part=part) for t in targets])
        return chosen(smooth_in_time(e, p.time_sigma)[keep], p.skip)

    def weights(self, fiducials: np.ndarray, targets: np.ndarray, keep: slice = slice(None),
                neutral: np.ndarray | None = None, gazes: np.ndarray | None = None) -> np.ndarray:
        """Video mode: the weights ((1 + parts) f + 1, n) a drive sums the photos with: the :meth:`expression`
        weights of the targets ``keep``, then each of the params' :attr:`~_Weights.parts`' own of the same
        targets (the eyes' with ``eye_gaze`` and the photos' ``gazes``, times gaze.ahead), then those of B's
        ``neutral`` (by default the photos' mean fiducials), whose blend sets how much fine detail
        :meth:`finish` gives back, and with ``detail_from`` neutral which, in every frame alike."""
        p = self.params
        looking = ahead(gazes, p.eye_gaze) if gazes is not None and p.eye_gaze else 1.0
        own = [self.expression(fiducials, targets, keep, part=part) * (looking if part == "eyes" else 1.0)
               for part in self.params.parts]
        rest = mean_shape(fiducials) if neutral is None else np.asarray(neutral, np.float64)
        return np.vstack([self.expression(fiducials, targets, keep), *own, self.expression(fiducials, rest[None])])

    def sums(self, fiducials: np.ndarray, targets: int, totals: BlendTotals) -> BlendSums:
        """Empty sums for the :meth:`weights` of ``targets`` frames: each part's own rows summed only over the
        band of image rows that holds its region and what the pyramid's collapse carries into it (REGION_MARGIN
        texels either side): the eyes' a fifth of the face's height, the brows' its top two fifths."""
        parts, shape, neutral = self.params.parts, totals.weighted[0].shape[:2], mean_shape(fiducials)
        bands = {}
        for k, part in enumerate(parts, start=1):
            inside = np.flatnonzero(REGIONS[part](neutral, shape).max(axis=1) > 0)
            if len(inside):
                band = (max(int(inside[0]) - REGION_MARGIN, 0), min(int(inside[-1]) + 1 + REGION_MARGIN, shape[0]))
                bands.update({t: band for t in range(k * targets, (k + 1) * targets)})
        return BlendSums.zeros((1 + len(parts)) * targets + 1, totals, bands)

    def finish(self, sums: BlendSums, totals: BlendTotals, fiducials: np.ndarray, targets: np.ndarray, *,
               close_eyes: bool | None = None, gaze: np.ndarray | None = None) -> np.ndarray:
        """Video mode: the textures (f, H, W, 3) float32 in 0-255 of the targets (f, 49, 2) from the
        sums over every photo (fiducials (n, 49, 2)) of their :meth:`weights` (B's neutral last). Each
        fine band of every texture is multiplied by one factor, the one that gives back ``detail_share``
        of the energy the neutral's blend lost (BlendSums.detail_gains): the detail given back does not
        change from frame to frame with the photos a frame takes. With ``brow_sigma``, the region above the
        eyes (brows.region) is the blend of the brows' own weights; with ``eye_sigma``, the eyes' region
        (eyes.region) is the blend of the eyes' own weights, given back its own fine bands: B's neutral's
        would draw B's neutral lids back over photos whose eyes are wider or narrower. With ``close_eyes``
        (default: the param), the eyes a target shuts drawn shut."""
        p, f = self.params, len(targets)
        neutral = mean_shape(fiducials)  # the texture's geometry is B's neutral: the photos' mean fiducials
        last = len(sums.num[0]) - 1
        gains = sums.detail_gains(totals, p.detail_share, last, finest=p.finest_share)
        held = last if p.detail_from == "neutral" else None
        textures = np.clip(sums.finish(totals, gains=gains, rows=range(f), held=held), 0, 255)
        for k, part in enumerate(self.params.parts, start=1):  # each part's own rows, after the frames' (weights)
            # the eyes take back their own fine detail (B's neutral's would draw its lids back), the brows the face's
            own = np.clip(sums.finish(totals, gains=gains, rows=range(k * f, (k + 1) * f),
                                      held=None if part == "eyes" else held), 0, 255)
            where = REGIONS[part](neutral, textures.shape[1:3])[..., None]
            textures += where * (own - textures)
        return _eyes_moved(textures, targets, neutral, p, gaze, p.close_eyes if close_eyes is None else close_eyes)

    def blend(self, cache: BlendCache, fiducials: np.ndarray, targets: np.ndarray, *, close_eyes: bool | None = None,
              gaze: np.ndarray | None = None, gazes: np.ndarray | None = None) -> np.ndarray:
        """Video mode with the whole cache in memory: the textures (f, H, W, 3) float32 of targets
        (f, 49, 2), or the texture (H, W, 3) of one target (49, 2), from a cache of photos aligned to
        their mean fiducials, whose own fiducials (n, 49, 2) give the expression weights
        (:meth:`weights`, with the photos' ``gazes``; :meth:`finish`; ``gaze``, (f, 2, 2) or (2, 2),
        moves the irises)."""
        targets = np.asarray(targets, np.float64)
        every = targets.reshape(-1, *targets.shape[-2:])
        weights = self.weights(fiducials, every, gazes=gazes)
        sums = self.sums(fiducials, len(every), cache.totals)
        sums.add(cache.weighted, cache.detail, weights)
        gaze = None if gaze is None else np.reshape(gaze, (len(every), 2, 2))
        out = self.finish(sums, cache.totals, fiducials, every, close_eyes=close_eyes, gaze=gaze)
        return out.reshape(*targets.shape[:-2], *out.shape[1:])

    def synthesize(self, photos, target, flow=None, reference=None):
        aligned = self.params.aligned(photos, target, flow, reference)
        # the photos are aligned to the target itself: its eyes are already as open as the target's
        texture = self.blend(self.cache(aligned), photos.fiducials, target, close_eyes=False)
        return Texture(texture, aligned.valid.any(axis=0))


class StaticTexture(TextureBackend):
    name = "static"
    description = "baseline (ii) of the paper's Fig. 5: one static average of the collection, TPS-warped to the target"

    class Params(_Alignment):
        pass

    def synthesize(self, photos, target, flow=None, reference=None):
        p = self.params
        mean_fiducials = mean_shape(photos.fiducials)
        aligned = p.aligned(photos, mean_fiducials, flow)
        average = _weighted_mean(aligned.rgb, aligned.valid.astype(np.float32))
        warp = tps_map(target, mean_fiducials, (H, W), lam=p.tps_lambda, step=4)
        rgb = cv2.remap(average.rgb, warp[..., 0], warp[..., 1], cv2.INTER_LINEAR)
        mask = cv2.remap(average.mask.astype(np.float32), warp[..., 0], warp[..., 1], cv2.INTER_LINEAR) > 0.99
        return Texture(rgb, mask)


class WeightedTexture(TextureBackend):
    name = "weighted"
    description = ("baseline (iii) of the paper's Fig. 5: the expression-weighted average of the rigidly "
                   "frontalized photos, no non-rigid alignment")

    class Params(_Weights):
        pass

    def synthesize(self, photos, target, flow=None, reference=None):
        return _expression_mean(align.rigid(photos), photos.fiducials, target, self.params)


class PrewarpedTexture(TextureBackend):
    name = "prewarped"
    description = ("baseline (iv) of the paper's Fig. 5: the expression-weighted average of the photos after "
                   "TPS and dense pre-warping to the target, at a single scale")

    class Params(_Alignment):
        pass

    def synthesize(self, photos, target, flow=None, reference=None):
        p = self.params
        aligned = p.aligned(photos, target, flow, reference)
        return _expression_mean(aligned, photos.fiducials, target, p)


@hookimpl
def persona_register_backends(register):
    for backend in (MultiscaleTexture, StaticTexture, WeightedTexture, PrewarpedTexture):
        register(backend)
