"""Kind ``mouth``: the inside of B's mouth from B's own open-mouth photos (:mod:`persona.plugins.face.mouth`).

* ``median`` (the default): the per-pixel median of B's open photos between their inner lips, the widest or
  the darkest there as the render's ``mouth_choice`` says; each frame's share of B's teeth from the grey of
  the driver's own mouth against its nose, made steady in time.

It records "-" in its cache key (``key_name``), with the version the mouth stage had before it had a backend
to choose, so that stores made before stay valid.
"""

from __future__ import annotations

import numpy as np

from ..base import Params
from ..face import mouth
from ..face.dynamics import smooth_in_time
from ..hookspecs import hookimpl
from ..kinds import Mouth, MouthBackend, MouthInterior


class MedianMouth(MouthBackend):
    name = "median"
    description = ("the per-pixel median of B's open photos between their inner lips, the widest or the darkest "
                   "(stages.render.params.mouth_*); teeth or cavity in each frame as the driver's mouth shows them")
    default = True
    key_name = "-"
    version = "2"

    class Params(Params):
        pass

    def interior(self, photos, *, count, min_gap, choice):
        if choice not in ("widest", "darkest", "driver"):
            raise ValueError(f"mouth: choice must be widest, darkest or driver, got {choice!r}")
        points, landmarks = np.asarray(photos.points, np.float64), np.asarray(photos.landmarks, np.float64)
        open_ = mouth.widest(points, count if choice == "widest" else len(points), min_gap)  # widest first
        samples = [mouth.sample(photos.photos[int(i)], points[i]) for i in open_]
        widest = np.arange(min(len(open_), count))
        darkest = mouth.darkest(np.stack(samples), count) if samples else widest

        def made(keep) -> MouthInterior | None:
            if not len(keep):
                return None
            image = mouth.interior(samples[k] for k in keep).round().astype(np.uint8)
            return MouthInterior(image, np.nanmedian(mouth.lip_gap(landmarks[open_[keep]], per_iod=False)))

        return Mouth(made(darkest if choice == "darkest" else widest), made(darkest) if choice == "driver" else None,
                     mouth.lip_curves(np.nanmean(landmarks, axis=0)))

    def teeth(self, frames, sigma):
        return smooth_in_time(np.array([mouth.teeth_share(image, points) for image, points in frames], np.float64),
                              sigma)


@hookimpl
def persona_register_backends(register):
    register(MedianMouth)
