"""The expression a driver holds through its clip, and how much of it reaches the puppet.

A gain (the slope of the output's signal on the driver's) sees only how the expression moves
within the clip. A driver who smiles or looks surprised throughout also *holds* an expression:
the mean of each signal over the clip, against the driver's resting face. For every run folder
given, prints per signal (mouth opening, mouth width, eye openness, brow height, in inter-ocular
distances):

- A: the mean of dlib's reading of the driver's frames (the run's ``series.json``) less dlib's
  reading of A's mean face (``driver_mean_face.png``, the mean of A's photo collection);
- B: the mean of dlib's reading of the face alone, less its reading of B's neutral texture
  (``puppet_texture_neutral.png``).

B close to A means the held expression reached the puppet (docs/expression.md, "The driver's
neutral from its collection"). Both resting faces are means of many photos, read at twice their
size; their readings are a little softer than a single photo's.

    python benchmarks/held_expression.py runs/obama_mead_surprised runs/bush_obama
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from persona.plugins.builtin.evaluate import expression_signals
from persona.plugins.builtin.landmarks import DlibLandmarks
from persona.stores import media

SIGNALS = ("mouth_open", "mouth_width", "eye_open", "brow_height")


def resting(detector: DlibLandmarks, path: Path) -> dict[str, float]:
    """dlib's reading of the signals on one picture of a mean face, at twice its size."""
    image = media.decode_image(path)
    big = cv2.resize(image, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
    points = detector.detect(np.ascontiguousarray(big)).points / 2
    return {k: float(v[0]) for k, v in expression_signals(points[None]).items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="output folders of finished 3D runs")
    args = parser.parse_args()
    detector = DlibLandmarks()
    print("| run | " + " | ".join(f"{k} A / B" for k in SIGNALS) + " |")
    print("|---|" + "---|" * len(SIGNALS))
    for run in args.runs:
        series = json.loads((run / "series.json").read_text())
        a, b = resting(detector, run / "driver_mean_face.png"), resting(detector, run / "puppet_texture_neutral.png")
        cells = [f"{np.nanmean(np.asarray(series[f'driver_{k}'], float)) - a[k]:+.3f} / "
                 f"{np.nanmean(np.asarray(series[f'output_{k}'], float)) - b[k]:+.3f}" for k in SIGNALS]
        print(f"| {run.name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
