"""Kind ``transfer``: the driver's motion carried onto B's face (:mod:`persona.plugins.face.transfer`).

* ``deformation`` (the default): the magnitude-adjusted deformation transfer (paper §4, ALGORITHMS §10),
  B's mesh then moved so that its fiducials land on the retargeted ones (smoothed over time) and kept from
  folding below the mouth, as its params say.

It records "-" in its cache key (``key_name``), with the version the motion stage had before the transfer
had a backend to choose, so that stores made before stay valid.
"""

from __future__ import annotations

import numpy as np

from ..face.dynamics import smooth_in_time
from ..face.transfer import DeformationTransfer, FiducialFollow, TransferParams, below_mouth, lower_lip, unfolded
from ..hookspecs import hookimpl
from ..kinds import TransferBackend


class DeformationTransferBackend(TransferBackend):
    name = "deformation"
    description = ("the magnitude-adjusted deformation transfer (paper §4, ALGORITHMS §10), B's fiducials then "
                   "moved onto their retargeted places and the skin below the mouth kept from folding")
    default = True
    key_name = "-"
    version = "8"  # 7: the brows held up in full from eyes.SHUT_AT 0.3; 8: the inner lips parted as a step (split_lips)
    Params = TransferParams

    def prepare(self, pair):
        p = self.params
        transfer = DeformationTransfer(pair.driver_mean, pair.correspondence, pair.puppet, pair.puppet_mask,
                                       pair.driver_mask, params=p, denoiser=pair.denoiser)
        below = below_mouth(pair.puppet_mask, pair.fiducials) if p.unfold else None
        fold = None if below is None else (below, lower_lip(below, pair.fiducials))
        follow = targets = None
        if p.fiducials:
            follow = FiducialFollow(pair.fiducials, pair.puppet_mask, lam=p.fiducial_lambda,
                                    corner_reach=p.corner_reach, brow_hold=p.brow_hold, split_lips=p.split_lips)
            targets = smooth_in_time(np.asarray(pair.targets, np.float64), p.fiducial_sigma)

        def mesh(t: int, driver_mesh: np.ndarray) -> np.ndarray:
            out = transfer(driver_mesh) if follow is None else follow(transfer(driver_mesh), targets[t], p.fiducials)
            return out if fold is None else unfolded(out, fold[0], p.unfold_step, lip=fold[1])

        return mesh


@hookimpl
def persona_register_backends(register):
    register(DeformationTransferBackend)
