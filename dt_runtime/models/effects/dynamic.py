"""`dynamic`: speed-dependent error at the stop."""
from __future__ import annotations

import numpy as np

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs, approach


class Dynamic(Effect):
    """Speed-dependent error at the stop: lag along the approach and sag along -z, both ~ v
    (the direction of approach read from the previous row, rows in time order)."""

    name = "dynamic"
    columns = ("speed",)
    needs_chain = False
    factor = "the commanded speed and direction of travel"
    varies_with = ("speed", "direction")

    def regressors(self, inp: Inputs, chain: Chain | None = None) -> Block:
        """The block: a lag along the direction of travel and a sag in z, each proportional to speed.

        Parameters
        ----------
        inp : Inputs
            The data's columns (commanded TCP in time order, speed).
        chain : Chain, optional
            Not used.

        Returns
        -------
        Block
            Parameters lag and sag, s.
        """
        d = approach(inp.commanded)
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        u = np.divide(d, norm, out=np.zeros_like(d), where=norm > 0)
        v = inp.column("speed")[:, None]
        lag = -(v * u)
        sag = np.zeros_like(lag)
        sag[:, 2] = v[:, 0]  # actual lower by sag*v -> e_z = +sag*v
        return Block(self.name, np.stack([lag, sag], axis=2), ("lag", "sag"), ("s", "s"))
