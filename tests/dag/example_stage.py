"""A stage added the way docs/stages.md shows: this module and one record in the list, nothing else.

``brightness``: the mean brightness of each frame of a drive's composite, one number per frame, in the
drive's ``example/brightness``. tests/dag/test_plan.py adds :data:`BRIGHTNESS` to the list and runs it.
"""

import numpy as np

from persona.dag import stages as st
from persona.stores.layout import Collection

BRIGHTNESS = st.Stage(
    "brightness", ("drive",), (), "each composite frame's mean brightness", "drive",
    needs=("composite",), done=("example/brightness",), version="1", run="example_stage:run_brightness",
    runs="the client")


def run_brightness(runner, stage: st.Stage, target) -> None:
    """Done when ``example/brightness`` was made from the composite the drive holds now; else made anew."""
    drive = Collection(runner.root, target.path)
    prov = st.provenance(stage.name, params={}, inputs={"composite": target.made["composite"].key},
                         persona_version=runner.version)
    target.made[stage.name] = prov
    if st.is_done(drive, prov, *stage.done):
        return
    rgb = drive.array("composite/rgb")
    means = np.concatenate([rgb[start:stop].mean(axis=(1, 2, 3)) for start, stop in drive.shard_ranges()])
    drive.create_single("example/brightness", means.astype(np.float32), ("frame",), prov)
