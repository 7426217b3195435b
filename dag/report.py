"""report.html: one self-contained page a person reads in a browser.

Pictures are embedded as PNG data URIs, plots are drawn with matplotlib, and the
side-by-side video is embedded when it is small enough to keep the page light.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import cv2
import numpy as np

from persona.plugins.builtin.evaluate import BIAS_SCALE, ERROR_SCALE, GAIN_BLOCK, expression_peaks
from persona.plugins.face import composite
from persona.plugins.face.gaze import APART_SNR
from persona.stores import media, storage
from persona.stores.layout import Cast, Collection
from persona.stores.paths import item

from .stages import accepted, render_alpha

MAX_EMBEDDED_VIDEO = 40 * 2**20
#: the largest puppet.glb the page embeds for its 3D view (a 300-frame drive is about 17 MB)
MAX_EMBEDDED_MODEL = 48 * 2**20
#: the 3D view's WebGL viewer, shipped with the package and inlined into the page
VIEWER = Path(__file__).with_name("viewer.js")


#: zlib's level for the page's pictures, made again by every run: 3 encodes them in about a third of the time
#: of PIL's default, 6, for about 8 % more bytes, in a page that embeds its videos anyway
PNG_LEVEL = 3


def _png(image: np.ndarray) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=PNG_LEVEL)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _figure(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _img(src: str, alt: str, width: int | None = None) -> str:
    w = f' width="{width}"' if width else ""
    return f'<img src="{src}" alt="{html.escape(alt)}"{w}>'


def plots(series: dict, threshold: float, fps: float) -> dict[str, str]:
    """Per-frame identity distances, expression signals and, where the series has them, gaze, driver against
    output, and a self-reenactment's PSNR of each frame against its targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = {}
    t = np.arange(len(series["distance_to_b"])) / fps
    if np.isfinite(np.asarray(series["distance_to_b"], float)).any():  # none where identity is not judged
        fig, ax = plt.subplots(figsize=(9, 2.8))
        for name, label in (("distance_to_b", "to B (puppet)"), ("distance_to_a", "to A (driver)")):
            distance = np.asarray(series[name], float)
            judged = np.isfinite(distance)  # the frames described (evaluate.identity_frames)
            ax.plot(t[judged], distance[judged], label=label, lw=1)
        ax.axhline(threshold, color="k", ls="--", lw=0.8, label=f"same-person threshold {threshold:g}")
        ax.set(xlabel="seconds", ylabel="descriptor distance", title="Identity of the output frames judged")
        ax.legend(loc="upper right", fontsize=8)
        out["identity"] = _figure(fig)
        plt.close(fig)
    def driver_against_output(names, unit, title, height):
        fig, axes = plt.subplots(len(names), 1, figsize=(9, height), sharex=True)
        for ax, name in zip(axes, names):
            ax.plot(t, series[f"driver_{name}"], label="driver (A)", lw=1)
            ax.plot(t, series[f"output_{name}"], label="output (B)", lw=1)
            ax.set_ylabel(f"{name.replace('_', ' ')} / {unit}", fontsize=8)
        axes[0].legend(loc="upper right", fontsize=8)
        axes[0].set_title(title)
        axes[-1].set_xlabel("seconds")
        picture = _figure(fig)
        plt.close(fig)
        return picture

    out["expression"] = driver_against_output(("mouth_open", "mouth_width", "mouth_corners", "eye_open", "brow_height"),
                                              "IOD", "Expression: driver against output", 10)
    if "driver_gaze_along" in series:  # where the eyes look (evaluate.gaze_signals)
        out["gaze"] = driver_against_output(("gaze_along", "gaze_apart"), "eye width", "Gaze: the irises along the "
                                            "eye (+: the image's right) and the eyes apart (-: crossed)", 4.4)
    if "psnr_composite" in series:  # a self-reenactment: each frame against the real one
        fig, ax = plt.subplots(figsize=(9, 2.8))
        for name, label, key in (("psnr_composite", "composite.mp4", "psnr_db_composite"),
                                 ("psnr_face_alone", "the face alone", "psnr_db")):
            line, = ax.plot(t, series[name], label=label, lw=1)
            ax.axhline(_FIDELITY[key], color=line.get_color(), ls="--", lw=0.8)
        ax.set(xlabel="seconds", ylabel="PSNR / dB", title="Self-reenactment: each frame against the real one "
               "(dashed: the targets)")
        ax.legend(loc="lower right", fontsize=8)
        out["fidelity"] = _figure(fig)
        plt.close(fig)
    return out


def least_like_the_frame(series: dict) -> list[tuple[str, int]]:
    """In a self-reenactment, the frame whose composite is furthest from the real one (lowest PSNR), as a peak
    of the report's strip; none otherwise."""
    psnr = np.asarray(series.get("psnr_composite", np.nan), np.float64)
    return [("least like the real frame", int(np.nanargmin(psnr)))] if np.isfinite(psnr).any() else []


def met(value, target) -> bool | None:
    """Whether ``value`` lies within ``target`` (lo, hi), either end None for open; None where there is no
    target or no value."""
    if target is None or not isinstance(value, (int, float)) or value != value:
        return None
    lo, hi = target
    return (lo is None or value >= lo) and (hi is None or value <= hi)


def _table(rows: list[tuple]) -> str:
    """Rows of (label, value), (label, value, what is good) or (label, value, what is good, target): a
    table, the guide in a third column and, where a row has a target, whether it is met in a fourth."""
    def fmt(v):
        if v is None:  # a figure this run does not give (identity where the puppet is the driver)
            return "–"
        if isinstance(v, float):
            return f"{v:.3f}"
        return html.escape(str(v))

    marks = {True: "<td style='color:#070;white-space:nowrap'>met</td>",
             False: "<td style='color:#b00;white-space:nowrap'><b>not met</b></td>",
             None: "<td></td>"}
    body = "".join(f"<tr><th>{html.escape(r[0])}</th><td>{fmt(r[1])}</td>"
                   + (f"<td>{html.escape(r[2])}</td>" if len(r) > 2 else "")
                   + (marks[met(r[1], r[3])] if len(r) > 3 else "") + "</tr>" for r in rows)
    return f"<table>{body}</table>"


def _missed_by(value: float, target: tuple) -> str:
    """A missed figure with two decimals, or as many more (up to four) as it takes not to round onto the
    bound it misses: a gain of 0.696 against 0.7 reads 0.696, not 0.70."""
    for digits in (2, 3, 4):
        text = f"{value:.{digits}f}"
        if not met(float(text), target):
            break
    return text


def targets_summary(rows: list[tuple]) -> str:
    """One line over :func:`figure_rows`: how many of its targets are met, and which are not."""
    judged = [(r[0], r[1], r[3]) for r in rows if met(r[1], r[3]) is not None]
    missed = [f"{label} {_missed_by(value, target)}" for label, value, target in judged if not met(value, target)]
    line = f"{len(judged) - len(missed)} of {len(judged)} targets met"
    return line + (f"; not met: {'; '.join(missed)}." if missed else ".")


#: what is good for each stability figure, and its target where there is one
_STABILITY = {"jitter_ratio": "lower is better; target ≤ 1 (the output as steady as the driver), over the 51 "
                              "points inside the jaw line: the face alone shows no jaw",
              "jitter_ratio_composite": "the same on composite.mp4 (B's face in A's frame, A's jaw line), all 68",
              "colour_change_ratio": "lower is better; target ≤ 1; the face's mean colour, both mouths left out "
                                     "(an opening mouth changes it by what it shows: expression, not flicker)",
              "colour_change_ratio_composite": "the same on composite.mp4, in A's light made steady in time",
              "texture_change_ratio": "lower is better; ≤ 1: B's texture changes no more than A's face does"}
#: the composite's seam figures: (label, key, what is good, target, its bound)
_SEAM = (("colour step beyond the driver's own (grey levels)", "colour_step",
          "lower is better; 0 = no step beyond the frame's", "7.7 (3 % of 255)", 7.7),
         ("gradient energy over the driver's", "gradient_ratio", "lower is better; 1 = as smooth as the frame",
          "1.2", 1.2))
#: an expression signal of the driver's must range over more than this (IOD, 5th-95th percentile) for its
#: gain to have a target: below it the signal is dlib's noise (eyes that barely move, corners that
#: barely lift)
SIGNAL_RANGE = 0.05


#: the driver's gaze must range over more than this (eye widths, 5th-95th percentile) for its gain to have a
#: target: an iris that moves less than a tenth of the eye is a driver looking ahead
GAZE_RANGE = 0.1


#: what each gaze signal (persona.plugins.builtin.evaluate.gaze_signals) is, in the report's words
GAZE_SIGNALS = {"along": "along the eye", "across": "across the eye",
                "apart": "the eyes apart (the right one's offset along less the left one's)"}


def _gaze_rows(figures: dict) -> list[tuple]:
    """Where the eyes look, output on driver: a row per place (face alone, composite.mp4) and signal. The eyes
    apart have a target only where the driver's turn against each other stands out from the measure's noise as
    the texture's gaze requires before it turns B's eyes apart (gaze.APART_SNR); below it B's eyes turn together."""
    rows = []
    for where, signals in figures.items():
        for k, a in signals.items():
            over = a.get("driver_over_noise", np.inf)  # an evaluation made before it was recorded: counted
            counted = a.get("driver_range", 0.0) > GAZE_RANGE and over >= APART_SNR
            if counted:
                guide = f"1 = the driver's amplitude; r {a['r']:.2f}; target 0.7-1.4"
            elif over < APART_SNR:
                guide = (f"1 = the driver's amplitude; no target: the driver's eyes turn apart no more than the "
                         f"measure's noise (spread {over:.1f} times it, under {APART_SNR}: B's eyes turn together)")
            else:
                guide = (f"1 = the driver's amplitude; no target: the driver's irises range over "
                         f"{a['driver_range']:.3f} eye widths ({k}), under {GAZE_RANGE}")
            rows.append((f"gaze gain ({where.replace('_', ' ')}): {GAZE_SIGNALS.get(k, k)}", a["gain"], guide,
                         (0.7, 1.4) if counted else None))
    return rows


#: the driver's creases between the brows (evaluate.crease_energy, 5th-95th percentile) must range over more than
#: this for the output's gain on them to mean anything: a frowning face ranges over 0.2-0.5, a face that never
#: creases there over a few thousandths (the skin's grain and the video's noise)
CREASE_RANGE = 0.05


def _crease_rows(figures: dict) -> list[tuple]:
    """The creases between the brows, output on driver: a row per place (face alone, composite.mp4); no target
    (issue 55 asks that they come when the driver's do: r near 1, and a gain that does not leave them on)."""
    rows = []
    for where, a in figures.items():
        guide = (f"1 = they deepen and smooth as far as the driver's; r {a['r']:.2f} (1: when the driver's do)"
                 if a.get("driver_range", 0.0) > CREASE_RANGE else
                 f"the driver's range {a['driver_range']:.3f}, under {CREASE_RANGE}: a face that does not crease there")
        rows.append((f"creases between the brows, gain ({where.replace('_', ' ')})", a["gain"], guide, None))
    return rows


def _moves(amplitude: dict) -> bool:
    """Whether the driver's expression signal of ``amplitude`` (ev.amplitude) ranges over more than
    SIGNAL_RANGE: below it the signal is dlib's noise, and neither its gain nor its correlation has a target."""
    return amplitude.get("driver_range", 1.0) > SIGNAL_RANGE


def _correlation_row(signal: str, r: float, amplitude: dict) -> tuple:
    """The output's correlation with the driver on one expression signal; the mouth's opening has a target
    where the driver's mouth opens further than its noise (SIGNAL_RANGE), as its gain has: a driver whose lips
    stay shut gives a correlation with dlib's noise."""
    label = f"expression correlation: {signal.replace('_', ' ')}"
    if signal != "mouth_open":
        return label, r, "higher is better", None
    if _moves(amplitude):
        return label, r, "higher is better; target ≥ 0.85", (0.85, None)
    return (label, r, f"higher is better; no target: the driver's mouth opening ranges over "
            f"{amplitude['driver_range']:.3f} IOD, under {SIGNAL_RANGE}", None)


def _gain_rows(where: str, amplitudes: dict) -> list[tuple]:
    rows = []
    for k, a in amplitudes.items():
        counted = _moves(a)
        guide = (f"1 = the driver's amplitude; r {a['r']:.2f}; target 0.7-1.4" if counted else
                 f"1 = the driver's amplitude; no target: the driver's {k.replace('_', ' ')} ranges over "
                 f"{a['driver_range']:.3f} IOD, under {SIGNAL_RANGE}")
        low, high = a.get("gain_interval", (float("nan"),) * 2)
        if np.isfinite(low) and np.isfinite(high):
            guide += (f"; 95 % interval {low:.2f}-{high:.2f} (the frames drawn again in runs of {GAIN_BLOCK}: "
                      "evaluate.gain_interval)")
        rows.append((f"expression gain {where}: {k.replace('_', ' ')}", a["gain"], guide,
                     (0.7, 1.4) if counted else None))
    return rows


def figure_rows(ev: dict) -> list[tuple]:
    """The evaluation's figures as (label, value, what is good / target, target) rows; the target is
    (lo, hi), either end None for open, or None where the figure has none."""
    identity = ev["identity"]
    judged = None if identity_caveat(ev) else (0.95, None)  # a self-reenactment's output is A
    rows = [("frames", ev["frames"], "", None),
            ("frames bridged (no face in the driver)", ev["bridged_frames"], "lower is better", None),
            ("frames whose identity is judged", identity.get("frames_judged", ev["frames"]),
             "evenly spaced (evaluate.identity_frames); = frames when that is 0", None),
            ("frames that are B and not A", identity.get("fraction_b_not_a"), "higher is better; target ≥ 0.95", judged),
            ("composite.mp4 frames that are B and not A", identity.get("fraction_b_not_a_composite"),
             "higher is better; target ≥ 0.95", judged),
            ("mean distance to B", identity.get("mean_distance_to_b"), "lower is better; < 0.6 = the same person", None),
            ("mean distance to A", identity.get("mean_distance_to_a"), "higher is better; > 0.6 = another person", None),
            ("distance between B's photos and A's (centroids)", identity.get("distance_b_to_a"),
             "> 0.6 = dlib tells them apart, so identity can be judged", None),
            ("output frames without a face", identity["frames_without_face"], "lower is better; target 0", (None, 0))]
    rows += [_correlation_row(k, v, ev.get("amplitude", {}).get(k, {})) for k, v in ev["expression"].items()]
    rows += _gain_rows("(output / driver)", ev.get("amplitude", {}))
    rows += _gain_rows("on composite.mp4", ev.get("amplitude_composite", {}))
    rows += _gaze_rows(ev.get("gaze", {}))
    rows += _crease_rows(ev.get("creases", {}))
    rows += [(f"held expression: {k.replace('_', ' ')} (driver / face alone / composite, IOD)",
              " / ".join(f"{h[who]:+.3f}" for who in ("driver", "output", "composite")),
              "the mean over the clip less the resting face (A's mean photo, B's neutral texture): a smile or "
              "surprise held throughout, which no gain sees; the face's near the driver's = it reached B (the resting "
              "faces are soft means: a few hundredths is none, and the mouth's opening can read 0.13 high; "
              "docs/expression.md)", None)
             for k, h in ev.get("held", {}).items()]
    rows += [(k.replace("_", " "), v, _STABILITY.get(k, "lower is better"),
              (None, 1.0) if k in _STABILITY else None) for k, v in ev["stability"].items()]
    for how, f in ev.get("composite", {}).items():  # composite.mp4's blend, and a plain paste to compare
        ours = how == "blend"
        rows += [(f"composite seam ({how}): {label}", f[key],
                  f"{good}; target ≤ {aim}" if ours else f"{good} (a plain paste, for comparison)",
                  (None, hi) if ours else None) for label, key, good, aim, hi in _SEAM]
    rows += [(f"sharpness: {k.replace('_', ' ')}", v, "fine detail over the driver's own face in its frame, at the "
              "video's size (σ 1-2 px); 1 = as sharp" + ("; target ≥ 0.8" if k == "face_alone" else ""),
              (0.8, None) if k == "face_alone" else None) for k, v in ev.get("sharpness", {}).items()]
    texture = ev.get("texture", {})
    rows += [(f"texture tears: {k.replace('_', ' ')}", v, "lower is better; the ratio (frames over B's photos) "
              "target ≤ 1" if k == "ratio" else "lower is better", (None, 1.0) if k == "ratio" else None)
             for k, v in texture.get("tears", {}).items()]
    rows += [(f"texture detail: {k.replace('_', ' ')}", v, "the ratio (frames over B's photos) target ≥ 0.6"
              if k == "ratio" else "band-pass energy; higher is sharper", (0.6, None) if k == "ratio" else None)
             for k, v in texture.get("detail", {}).items()]
    rows += _self_reenactment_rows(ev.get("self_reenactment", {}))
    rows += [(f"{who.replace('_', ' ')} follow A's landmarks: {k.replace('_', ' ')} (gain, r)",
              f"{a['gain']:.2f}, {a['r']:.2f}", "gain 1 = the driver's amplitude", None) for who, figures in
             ev.get("motion", {}).items() for k, a in figures.items()]
    return rows


#: a self-reenactment's targets: the composite (what a viewer sees) and the face alone on grey
_FIDELITY = {"psnr_db_composite": 27.0, "ssim_composite": 0.88, "psnr_db": 25.0, "ssim": None}


#: each landmark registration of a self-reenactment: what is measured, and how
_REGISTRATIONS = {
    "registration": ("face alone", "dlib's points on the face alone from the real frame's"),
    "registration_composite": ("composite.mp4", "dlib's points on the composite from the real frame's"),
    "registration_posed": ("the motion's fiducials", "B's 49 fiducials where the mesh and the pose put them, "
                           "before the face is drawn, from dlib's points on the real frame"),
}


def _self_reenactment_rows(figures: dict) -> list[tuple]:
    """The rows of a self-reenactment's figures: PSNR and SSIM of the face region against the real frames,
    the landmark registration per region (dlib's points on the output against the real frame's), whose
    targets are the composite's, what a viewer sees, and each part of the face's share of the composite's error."""
    rows = []
    for k, v in figures.items():
        if k == "error_share":  # where the composite's error lies, as error_map.png shows it
            rows += [(f"self-reenactment error share: {region}", share, "share of the composite's squared error "
                      "inside the face", None) for region, share in v.items()]
            continue
        if not k.startswith("registration"):
            aim = _FIDELITY.get(k)
            rows.append((f"self-reenactment {k}", v, "higher is better" + (f"; target ≥ {aim:g}" if aim else ""),
                         None if aim is None else (aim, None)))
            continue
        judged = k.endswith("_composite")
        what, guide = _REGISTRATIONS[k]
        for region, d in v.items():
            if np.isnan(d):  # a region the motion's fiducials do not have: the jaw line
                continue
            bound = 3.0 if region == "jaw" else 2.0
            rows.append((f"self-reenactment landmark registration ({what}): {region}", d,
                         guide + ", median % of the eye distance; lower is better" + (
                             f"; target ≤ {bound:g}" if judged else ""), (None, bound) if judged else None))
    return rows


def identity_caveat(ev: dict) -> str | None:
    """Why "B and not A" cannot judge identity in this run: the puppet is the driver, or dlib sees B and A
    as one person: the centroids of B's and A's photos lie within 0.6 of each other (figures before version
    7, which lack that distance: the output lies within 0.6 of both). An output that is near both while B's
    and A's photos are apart is judged: it is a figure, not a caveat."""
    identity = ev["identity"]
    if identity.get("judged") is False:
        return ("the puppet is the driver (a self-reenactment from one collection): B is A, so \"B and not A\" "
                "is not judged; PSNR and SSIM against A's frames are.")
    if "distance_b_to_a" in identity:
        apart = not identity["distance_b_to_a"] < 0.6
    else:
        near_a, near_b = identity.get("mean_distance_to_a"), identity.get("mean_distance_to_b")
        apart = near_a is None or near_b is None or not (near_a < 0.6 and near_b < 0.6)
    if apart:
        return None
    return ("dlib's descriptor puts B and A within 0.6 of each other, i.e. it sees them as one person: "
            "a self-reenactment (B is A), or synthetic faces, which the descriptor was not trained on. "
            "\"B and not A\" cannot judge identity here; PSNR and SSIM against A's frames (self-reenactment) can.")


#: the texture methods of paper Fig. 5, as the report names them
_TEXTURE_METHODS = {"reference": "reference photo", "static": "(ii) static average", "weighted": "(iii) weighted",
                    "prewarped": "(iv) prewarped", "multiscale": "ours (multiscale)"}


def texture_section(result: dict, grid: np.ndarray | None) -> list[str]:
    """The Fig. 5 table (one row per method) and picture grid of a texture evaluation."""
    head = ("<tr><th>method</th><th>alignment, median % IOD (lower is better)</th><th>no face found</th>"
            "<th>detail over the reference's (1 = as much)</th><th>fidelity, band-pass SSIM (higher is better)</th>"
            "<th>colour spread % (lower is better)</th></tr>")

    def cell(v, fmt):
        return "–" if v is None else format(v, fmt)

    rows = "".join(
        f"<tr><td>{html.escape(_TEXTURE_METHODS.get(name, name))}</td>"
        f"<td>{cell(r.get('alignment_median_pct_iod'), '.2f')}</td><td>{cell(r.get('no_face_found'), 'd')}</td>"
        f"<td>{cell(r.get('detail_median'), '.3f')}</td><td>{cell(r.get('fidelity_median'), '.3f')}</td>"
        f"<td>{cell(r.get('colour_spread_pct'), '.2f')}</td></tr>" for name, r in result["table"].items())
    target = "each reference photo" if result.get("mode") == "reference" else "each reference's fiducials"
    parts = [f"<h2>Texture synthesis (paper Fig. 5): {len(result['references'])} held-out references, "
             f"{result['collection_photos']} photos, target {html.escape(target)}</h2>", f"<table>{head}{rows}</table>"]
    if grid is not None:
        parts.append(_img(_png(grid), "reference | ii | iii | iv | ours", min(960, grid.shape[1])))
    return parts


def collection_pictures(coll: Collection, mean: np.ndarray | None, output, n_faces: int = 60) -> dict[str, str]:
    """A collection's mean aligned face (x2) and a contact sheet of its first accepted aligned faces,
    written into ``output`` as ``<collection>_mean_face.png`` and ``<collection>_contact_sheet.png``."""
    slug = coll.path.replace("/", "_")
    written = {}
    if mean is not None:
        big = np.kron(np.clip(mean, 0, 255).round().astype(np.uint8), np.ones((2, 2, 1), np.uint8))
        written["mean_face"] = storage.join(output, f"{slug}_mean_face.png")
        media.write_png(written["mean_face"], big)
    ok = accepted(coll)
    faces = []
    for start, stop in coll.shard_ranges():  # whole shards: slices read fast, selections do not
        if len(faces) >= n_faces:
            break
        if ok[start:stop].any():
            faces += list(coll.array("aligned/rgb")[start:stop][ok[start:stop]])
    if faces:
        written["contact_sheet"] = storage.join(output, f"{slug}_contact_sheet.png")
        media.write_png(written["contact_sheet"], media.contact_sheet(faces[:n_faces], columns=10))
    return {k: str(v) for k, v in written.items()}


def collection_images(metrics: dict) -> dict[str, np.ndarray]:
    """The PNG pictures a run's collections wrote (metrics.json's ``collections``), by title."""
    return {f"{path}: {kind.replace('_', ' ')}": media.decode_image(file, max_side=4000)
            for path, c in metrics["collections"].items() for kind, file in c["pictures"].items()
            if str(file).endswith(".png") and storage.isfile(file)}


def frames_strip(drive: Collection, frames: Collection, n: int = 6, side: int = 240, at=None) -> np.ndarray:
    """``n`` frames spread over the drive (or the frames ``at``), a column each: the driver's frame
    (top), the composite as composite.mp4 has it (middle), the puppet alone as puppet.mp4 has it
    (bottom); each cropped to a square about the rendered face and shown ``side`` px wide."""
    columns = []
    for i in np.linspace(0, drive.n - 1, min(n, drive.n)).round().astype(int) if at is None else at:
        alpha = render_alpha(drive.array("render/mask")[i])  # the frames, render and composite share the canvas
        images = [frames.array("photos/rgb")[i], drive.array("composite/rgb")[i],
                  composite.alone(drive.array("render/rgb")[i], alpha)]
        ys, xs = np.nonzero(alpha > 0)
        if len(ys):  # a square 1.5 times the face's larger side about its middle, moved inside the frame
            h, w = alpha.shape
            size = min(int(1.5 * max(np.ptp(ys), np.ptp(xs))) + 2, h, w)
            y0 = int(np.clip((ys.min() + ys.max() - size) // 2, 0, h - size))
            x0 = int(np.clip((xs.min() + xs.max() - size) // 2, 0, w - size))
            images = [im[y0:y0 + size, x0:x0 + size] for im in images]
        columns.append(np.concatenate([cv2.resize(im, (side, side), interpolation=cv2.INTER_AREA)
                                       for im in images], axis=0))
    return np.concatenate(columns, axis=1)


#: the title of a self-reenactment's error map (evaluate.ErrorSums.picture)
ERROR_TITLE = ("Where the self-reenactment differs from the real frames: their mean (left); the composite's "
               f"root-mean-square difference from them at each pixel (middle: blue 0, red {ERROR_SCALE:.0f} grey "
               "levels and over); and its mean difference, real less composite (right: green 0, red where the "
               f"composite is {BIAS_SCALE:.0f} levels darker on average, blue where it is as much lighter: its light "
               "or tone rather than its detail)")


def write_run_report(wf, root, metrics: dict, series: dict | None, *, cast: Cast | None = Cast(),
                     output=None) -> Path | str:
    """report.html in ``output`` (the workflow's output folder by default), from a run's ``metrics``
    (metrics.json), its store (pictures, and the frame strip of the drive of ``cast``, also written as
    frames.png; none when ``cast`` is None or its drive is not in the store) and ``series`` (the
    plots); with every texture evaluation found in the folder, and the 3D view of the drive's puppet.glb
    when the folder has it."""
    out = wf.output if output is None else output
    pictures = collection_images(metrics)
    strip = peaks = None
    if cast is not None and root.get(cast.drive) is not None:
        drive, frames = Collection(root, cast.drive), Collection(root, cast.frames)
        strip = frames_strip(drive, frames)
        media.write_png(storage.join(out, "frames.png"), strip)
        if series:  # the driver's expression peaks, driver above output
            found = expression_peaks({k.removeprefix("driver_"): v for k, v in series.items()
                                         if k.startswith("driver_")}) + least_like_the_frame(series)
            peaks = (found, frames_strip(drive, frames, side=200, at=[t for _, t in found]))
        error = storage.join(out, "error_map.png")  # a self-reenactment's (dag.outputs.write_pictures)
        if storage.isfile(error):
            pictures = {ERROR_TITLE: media.decode_image(error, max_side=4000), **pictures}
    fps = float(root[cast.frames].attrs["fps"]) if strip is not None else 25.0
    model = storage.join(out, "puppet.glb")  # a 3D drive's, written with its videos: the 3D view's
    model = model if strip is not None and storage.isfile(model) else None
    texture = []
    for file in storage.glob(storage.join(out, "*_texture_evaluation*.json")):
        result = json.loads(storage.read_text(file))
        grid = result.get("grid")
        texture.append((result, media.decode_image(grid, max_side=4000) if grid and storage.isfile(grid) else None))
    return write_report(storage.join(out, "report.html"), metrics=metrics, pictures=pictures, strip=strip,
                        peaks=peaks, series=series, threshold=wf.evaluate.threshold, fps=fps,
                        videos=[storage.join(out, f"{name}.mp4") for name in ("composite", "puppet", "side_by_side")],
                        texture=texture, model=model)


def write_report(path, *, metrics: dict, pictures: dict[str, np.ndarray], strip: np.ndarray | None,
                 series: dict | None, threshold: float, fps: float, videos: list = (),
                 texture: list[tuple[dict, np.ndarray | None]] = (),
                 peaks: tuple[list, np.ndarray] | None = None, model=None) -> Path | str:
    """Write the page atomically; ``pictures`` are titled images (means, contact sheets); ``videos``
    are embedded in their order (the composite first), each up to ``MAX_EMBEDDED_VIDEO`` bytes;
    ``texture``: the results of ``persona evaluate --texture`` (its JSON, and its picture grid); ``peaks``:
    the driver's expression peaks (evaluate.expression_peaks) and their :func:`frames_strip`; ``model``:
    the drive's .glb, shown by the 3D view (:func:`model_view`) after the videos."""
    parts = [f"<h1>Persona — {html.escape(str(metrics.get('workflow', '')))}</h1>"]
    if metrics.get("warnings"):
        items = [f"<li>{html.escape(str(w))}</li>" for w in metrics["warnings"]]
        parts += ["<h2>Warnings</h2><ul>", *items, "</ul>"]
    shown = [v for v in videos if storage.isfile(v) and storage.stat(v)[0] <= MAX_EMBEDDED_VIDEO]
    for v in shown:
        data = base64.b64encode(storage.read_bytes(v)).decode()
        title = storage.name(storage.with_suffix(v, "")).replace("_", " ")
        parts += [f"<h2>{html.escape(title)}</h2>",
                  f'<video controls loop width="720" src="data:video/mp4;base64,{data}"></video>']
    if model is not None:
        parts += model_view(model)
    ev = metrics.get("evaluation")
    if ev:
        rows = figure_rows(ev)
        caveat = identity_caveat(ev)
        if caveat:
            parts.append(f"<p><b>Identity:</b> {html.escape(caveat)}</p>")
        parts += ["<h2>Figures</h2>", f"<p><b>{html.escape(targets_summary(rows))}</b></p>", _table(rows)]
    for result, grid in texture:
        parts += texture_section(result, grid)
    if strip is not None:
        parts += ["<h2>Driver frames (top), the composite (middle), the puppet alone (bottom)</h2>", _img(_png(strip), "frames", min(960, strip.shape[1]))]
    if peaks is not None:
        found, image = peaks
        columns = ", ".join(f"{label} (frame {t})" for label, t in found)
        parts += ["<h2>The driver's expression peaks and widest head turns (and a self-reenactment's frame least "
                  "like the real one): "
                  "driver (top), composite (middle), puppet alone (bottom)</h2>",
                  f"<p>Left to right: {html.escape(columns)}.</p>", _img(_png(image), "peaks", min(1200, image.shape[1]))]
    if series:
        for name, src in plots(series, threshold, fps).items():
            parts.append(_img(src, name))
    for title, image in pictures.items():
        parts += [f"<h2>{html.escape(title)}</h2>", _img(_png(image), title, min(960, image.shape[1]))]
    counts = [(f"{c}: {item(c)}s aligned", f"{v['accepted']} of {v['n_photos']}")
              for c, v in metrics.get("collections", {}).items()]
    timing = [(f"{r['collection']} {r['stage']} (wall s)", r["wall_seconds"]) for r in metrics.get("stages", [])]
    timing += [(f"{c}: subspace, alignment, shape and texture (wall s)", v["shape_seconds"])
               for c, v in metrics.get("collections", {}).items() if v.get("shape_seconds") is not None]
    extra = [(k, v) for k, v in metrics.get("speed", {}).items()]
    parts += ["<h2>Counts and timing</h2>", _table(counts + extra + timing), *rejected_section(metrics),
              "<details><summary>metrics.json</summary><pre>"
              + html.escape(json.dumps(metrics, indent=2, default=str)) + "</pre></details>"]
    media.write_bytes(path, _page("Persona report", parts).encode())
    return path


def model_view(model) -> list[str]:
    """The page's 3D view of a drive's .glb: the file embedded (base64) and the WebGL viewer (viewer.js)
    inlined, so the page still needs no network and no server; a line naming the file beside the page
    when it is too large to embed."""
    size = storage.stat(model)[0]
    title = "<h2>The puppet in 3D (drag to turn it; puppet.glb opens in Blender and web viewers)</h2>"
    if size > MAX_EMBEDDED_MODEL:
        return [title, f"<p>puppet.glb ({size / 2**20:.0f} MB) is beside this page, too large to show in it.</p>"]
    data = base64.b64encode(storage.read_bytes(model)).decode()
    return [title, '<div class="persona-3d" data-glb="persona-glb" data-width="480" data-height="480"></div>',
            f'<script type="application/octet-stream" id="persona-glb">{data}</script>',
            f"<script>{VIEWER.read_text()}</script>"]


def rejected_section(metrics: dict, shown: int = 12) -> list[str]:
    """The report's list of rejected photos: per collection, each reason with how many photos it rejected
    and their names (the first ``shown``); nothing when every photo was taken."""
    rows = [(f"{c}: {reason}", f"{len(ids)}: " + ", ".join(ids[:shown]) + (f" and {len(ids) - shown} more"
                                                                          if len(ids) > shown else ""))
            for c, v in metrics.get("collections", {}).items() for reason, ids in v.get("rejections", {}).items()]
    return ["<h2>Rejected photos</h2>", _table(rows)] if rows else []


def _page(title: str, parts: list[str]) -> str:
    """An HTML page of ``parts``, in the reports' style."""
    return ("<!doctype html><html><head><meta charset='utf-8'>"
            f"<title>{html.escape(title)}</title><style>"
            "body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}"
            "table{border-collapse:collapse}th,td{border-bottom:1px solid #ddd;padding:3px 10px;text-align:left;"
            "vertical-align:top}img,video{display:block;margin:0.5em 0;max-width:100%}</style></head><body>"
            + "\n".join(parts) + "</body></html>")


#: the batch page's columns: (heading, the figure's path in a drive's evaluation, its format)
_BATCH_FIGURES = (("B and not A", ("identity", "fraction_b_not_a_composite"), "{:.0%}"),
                  ("mouth open gain", ("amplitude", "mouth_open", "gain"), "{:.2f}"),
                  ("mouth width gain", ("amplitude", "mouth_width", "gain"), "{:.2f}"),
                  ("eye open gain", ("amplitude", "eye_open", "gain"), "{:.2f}"),
                  ("mouth corners gain", ("amplitude", "mouth_corners", "gain"), "{:.2f}"),
                  ("brow gain", ("amplitude", "brow_height", "gain"), "{:.2f}"),
                  ("jitter", ("stability", "jitter_ratio_composite"), "{:.2f}"))


def _figure_at(ev: dict, path: tuple) -> str:
    for key in path:
        ev = ev.get(key, {}) if isinstance(ev, dict) else {}
    return ev if isinstance(ev, (int, float)) else None


def write_batch_page(wf, metrics: dict) -> Path | str:
    """``index.html`` in the output folder of a version-2 workflow: every drive in a table — its
    puppet, driver and video, a poster (the driver's frame over the composite at the drive's middle
    frame), its headline figures (:data:`_BATCH_FIGURES`) or why it failed — each linking to the
    drive's own report; then every person's pictures."""
    from persona.stores.layout import open_store

    root = open_store(wf.store, mode="r")
    head = "".join(f"<th>{html.escape(h)}</th>" for h in ("drive", "poster", *(c[0] for c in _BATCH_FIGURES)))
    rows = []
    for plan in wf.drive_plans():
        d, c = metrics["drives"][plan.name], plan.cast
        title = (f'<a href="{html.escape(plan.name)}/report.html">{html.escape(plan.name)}</a><br>'
                 f"<small>{html.escape(c.puppet)} performing {html.escape(c.frames)}, driven by "
                 f"{html.escape(c.driver)}</small>")
        if d.get("error"):
            rows.append(f"<tr><td>{title}</td><td colspan='{1 + len(_BATCH_FIGURES)}'>failed: "
                        f"{html.escape(d['error'])}</td></tr>")
            continue
        drive = Collection(root, c.drive)
        poster = frames_strip(drive, Collection(root, c.frames), side=160, at=[drive.n // 2])[:320]
        cells = [(f.format(v) if (v := _figure_at(d["evaluation"], path)) is not None else "–")
                 for _, path, f in _BATCH_FIGURES]
        if identity_caveat(d["evaluation"]):  # dlib sees B and A as one person: no identity figure to give
            cells[0] = "not judged (B is A to dlib)"
        rows.append(f"<tr><td>{title}</td><td>{_img(_png(poster), plan.name)}</td>"
                    + "".join(f"<td>{html.escape(v)}</td>" for v in cells) + "</tr>")
    parts = [f"<h1>Persona — {html.escape(wf.name)}: {len(rows)} drives</h1>",
             "<p>Each drive's headline figures: B and not A and the jitter (over the driver's, target ≤ 1) "
             "on composite.mp4's frames, the expression gains on the face alone (puppet.mp4; 1 = the "
             "driver's amplitude, target 0.7-1.4). A drive's name opens its report.</p>",
             f"<table><tr>{head}</tr>{''.join(rows)}</table>", *rejected_section(metrics)]
    for title, image in collection_images(metrics).items():
        parts += [f"<h2>{html.escape(title)}</h2>", _img(_png(image), title, 480)]
    path = storage.join(wf.output, "index.html")
    media.write_bytes(path, _page(f"Persona batch: {wf.name}", parts).encode())
    return path
