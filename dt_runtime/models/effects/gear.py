"""`gear`: transmission error periodic in the joint angle."""
from __future__ import annotations

import numpy as np

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs


class Gear(Effect):
    """Transmission error periodic in joint angle: dq_j = sum_h a sin(h q_j) + b cos(h q_j),
    over the robot model's candidate harmonics (`gear_harmonics` in its config)."""

    name = "gear"
    columns = ("joints",)
    factor = "a periodic pattern in the joint angles"
    varies_with = ()

    def regressors(self, inp: Inputs, chain: Chain) -> Block:
        """The block: sin and cos of each candidate harmonic of each joint angle, through the Jacobian.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain
            The robot's kinematic chain.

        Returns
        -------
        Block
            Parameters q<j>_sin<h>, q<j>_cos<h>, rad.
        """
        J = chain.jacobian(inp.column("joints"))
        q = inp.column("joints")
        cols, names = [], []
        for j in range(J.shape[2]):
            for h in chain.gear_harmonics:
                for fn, lab in ((np.sin, "sin"), (np.cos, "cos")):
                    cols.append(-J[:, :, j] * fn(h * q[:, j])[:, None])
                    names.append(f"q{j + 1}_{lab}{h}")
        return Block(self.name, np.stack(cols, axis=2), tuple(names), ("rad",) * len(names))
