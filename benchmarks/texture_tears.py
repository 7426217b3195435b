"""Tears in B's texture: where they come from, and each video-mode alignment's neutral texture.

On a finished run's store, prints the tear figures of ``persona evaluate`` (docs/texture.md):
B's frontalized photos (the collection's own level), the same photos as the align stage's
collection flow warped them, the stored neutral texture and the frames' textures; then builds
the neutral texture (B at B's mean fiducials) again with each ``video_alignment`` of the
multiscale texture backend and prints its tears, its detail against the photos' and its time,
and writes the textures side by side to ``--picture``.

    python benchmarks/texture_tears.py workflows/obama_driven_by_mead_happy.yaml --picture tears.png
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from persona.dag.evaluate import own_photos, texture_figures
from persona.dag.texture import video_aligned
from persona.dag.workflow import load_workflow
from persona.plugins.builtin import evaluate as ev
from persona.plugins.builtin.texture import MultiscaleTexture
from persona.plugins.face.template import generic_template
from persona.stores import media
from persona.stores.layout import OK, Collection, open_store


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workflow")
    parser.add_argument("--picture", help="PNG: the neutral texture of each alignment, side by side")
    args = parser.parse_args()
    wf = load_workflow(args.workflow)
    root = open_store(wf.store, mode="r")
    print(wf.name, "stored:", json.dumps({k: {m: round(v, 3) for m, v in f.items()} for k, f in texture_figures(root).items()}))

    puppet = Collection(root, "puppet")
    ok = np.flatnonzero(puppet.state("align") == OK)
    target = puppet.array("aligned/mean_fiducials")[...].astype(np.float64)
    fiducials = puppet.rows("aligned/fiducials", ok).astype(np.float64)
    reference = own_photos(puppet)[3]
    face = generic_template().mask
    textures = []
    for alignment in ("collection", "own"):
        backend = MultiscaleTexture({**wf.stage("texture")[1], "video_alignment": alignment})
        start = time.perf_counter()
        neutral = backend.blend(backend.cache(video_aligned(puppet, ok, backend, alignment)), fiducials, target)
        seconds = time.perf_counter() - start
        print(f"video_alignment {alignment}: neutral texture's tears {ev.tear_energy(neutral, face, reference):.3f}, "
              f"detail {ev.detail_energy(neutral, face):.3f}, {seconds:.0f} s for {len(ok)} photos")
        textures.append(neutral.round().astype(np.uint8))
    if args.picture:
        media.write_png(args.picture, np.kron(np.concatenate(textures, axis=1), np.ones((2, 2, 1), np.uint8)))


if __name__ == "__main__":
    main()
