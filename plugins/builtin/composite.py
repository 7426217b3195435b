"""Kinds ``composite`` and ``light``: B's face in A's frame, in A's light (docs/composite.md).

* ``multiband`` (composite, the default): B's face matched to A's light and tone at its edge, A's
  hair left in front of it, then blended band by band through the mask
  (:func:`persona.plugins.face.composite.blend`; Burt & Adelson 1983).
* ``steady`` (light, the default): the planes the render fitted on each frame made steady in time, a
  median over the frames around then a Gaussian (:func:`persona.plugins.face.composite.steady_light`).

Both record "-" in their cache keys (``key_name``), with the versions their stages had before they
had backends to choose, so that stores made before stay valid.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..base import Params
from ..face.composite import blend, steady_light
from ..hookspecs import hookimpl
from ..kinds import CompositeBackend, LightBackend


class MultibandComposite(CompositeBackend):
    name = "multiband"
    description = ("B's face matched to A's light and tone at its edge, A's hair kept in front, then a "
                   "multi-band blend into A's frame (Burt & Adelson 1983; docs/composite.md)")
    default = True
    key_name = "-"
    version = "12"

    class Params(Params):
        lighting: float = Field(1.0, ge=0, le=1, description="how far B's face takes A's colour and light at its "
                                "edge before the multi-band blend into A's frame (composite.mp4; not in the paper, "
                                "which shows the puppet alone): 1 = matched at the edge and carried smoothly inward, "
                                "0 = B's render as it is (docs/composite.md)")
        tone: float = Field(1.0, ge=0, le=1, description="how much of A's mean skin tone B's face takes with the "
                            "light: 1 = all (no colour step at the edge), 0 = B's own mean tone kept, only the way A's "
                            "light varies along the edge matched (the blend spreads the rest; docs/composite.md)")
        tone_reach: float = Field(0.5, ge=0, le=0.5, description="how deep inside B's face (a fraction of its "
                                  "smaller side) its middle's tone is reached: at the edge B's face takes all of A's "
                                  "tone, so no step, and within the reach it passes smoothly to `tone`; 0 = `tone` up "
                                  "to the edge (docs/composite.md)")
        hair: float = Field(1.0, ge=0, le=1, description="how much of what is not A's skin inside B's edge stays in "
                            "front of B's face: A's hair (a fringe, strands at the temples) and the background beside "
                            "a turned head, all round but the chin: 1 = all, 0 = B's face covers it (docs/composite.md)")

    def composite(self, face, frame, alpha, *, plane, own=None, points=None):
        p = self.params
        return blend(face, frame, alpha, plane=plane, lighting=p.lighting, tone=p.tone, tone_reach=p.tone_reach,
                     hair=p.hair, own=own, points=points)


class SteadyLight(LightBackend):
    name = "steady"
    description = ("each frame's light at B's edge made steady in time: a median over the frames within 2σ, "
                   "then a Gaussian (docs/composite.md)")
    default = True
    key_name = "-"
    version = "1"

    class Params(Params):
        sigma: float = Field(3.0, ge=0, le=25, description="σ (frames) over which the light B's face takes is made "
                             "steady in time (a median over the frames within 2σ, then a Gaussian): fitted on each "
                             "frame alone it jumps where hair, glasses or a turned head pass under B's edge (the "
                             "face's colour from frame to frame on a driver with glasses: 1.8 -> 0.8 grey levels, "
                             "median; docs/composite.md). 0 = each frame's own")

    def light(self, planes):
        planes = np.asarray(planes)
        if planes.ndim != 3 or planes.shape[1:] != (4, 3):
            raise ValueError(f"light: planes must have shape (T, 4, 3), got {planes.shape}")
        return steady_light(planes, self.params.sigma)


@hookimpl
def persona_register_backends(register):
    register(MultibandComposite)
    register(SteadyLight)
