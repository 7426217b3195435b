"""Did a change move the expression gains, or only the drive's noise? Two runs of one drive compared.

Give the output folders of two finished runs of the same workflow (the second with the change: a
copy of the store run with ``--set store=... --set output=...`` and the setting to try). From each
run's ``series.json`` (the driver's, the face alone's and composite.mp4's signals, frame by frame), prints per
expression signal each run's gain with its 95 % interval, and the difference with its own interval,
judged on the same draws of frames for both runs (``evaluate.gain_difference``). A difference whose
interval leaves out 0 is the change's; one whose interval holds 0 may be the drive's noise, however
far apart the two gains look.

    python benchmarks/gain_difference.py ../runs/bush_obama /tmp/bush_obama_variant
    python benchmarks/gain_difference.py ../runs/bush_obama /tmp/bush_obama_variant --composite

``--composite`` judges composite.mp4's signals instead of the face alone's (for a change to the
composite, which leaves the face alone as it was).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from persona.plugins.builtin.evaluate import amplitude, gain_difference

SIGNALS = ("mouth_open", "mouth_width", "eye_open", "brow_height")


def series(folder: str) -> dict:
    path = Path(folder) / "series.json"
    if not path.is_file():
        raise SystemExit(f"{path}: not found; give the output folder of a finished run (persona run writes it)")
    return {k: np.asarray(v, np.float64) for k, v in json.loads(path.read_text()).items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", help="output folder of the run to compare against")
    parser.add_argument("second", help="output folder of the run with the change")
    parser.add_argument("--composite", action="store_true", help="composite.mp4's signals, not the face alone's")
    args = parser.parse_args(argv)
    a, b = series(args.first), series(args.second)
    view = "composite" if args.composite else "output"
    for folder, run in ((args.first, a), (args.second, b)):
        if f"{view}_mouth_open" not in run:
            raise SystemExit(f"{folder}/series.json has no {view} signals: its evaluation is older than them; "
                             "run `persona evaluate` on that workflow again")
    if len(a["driver_mouth_open"]) != len(b["driver_mouth_open"]):
        raise SystemExit(f"the runs have {len(a['driver_mouth_open'])} and {len(b['driver_mouth_open'])} frames: "
                         "not two runs of one drive")
    print(f"{'signal':<12} {'first':>22} {'second':>22} {'difference':>26}")
    for k in SIGNALS:
        driver = a[f"driver_{k}"]
        first, second = (amplitude(driver, run[f"{view}_{k}"]) for run in (a, b))
        diff = gain_difference(driver, a[f"{view}_{k}"], b[f"{view}_{k}"])
        shown = [f"{g['gain']:.3f} [{g['gain_interval'][0]:.2f}, {g['gain_interval'][1]:.2f}]" for g in (first, second)]
        low, high = diff["interval"]
        print(f"{k:<12} {shown[0]:>22} {shown[1]:>22} {diff['difference']:>+9.3f} [{low:+.3f}, {high:+.3f}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
