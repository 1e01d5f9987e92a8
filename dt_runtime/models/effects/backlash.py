"""`backlash`: play in the joints, against the direction of approach."""
from __future__ import annotations

import numpy as np

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs, approach


class Backlash(Effect):
    """Half the play against the direction of approach: dq_j = -(w_j / 2) sign(dq_j), the
    direction read from the previous row (rows in time order)."""

    name = "backlash"
    columns = ("joints",)
    factor = "the direction from which each joint approached"

    def regressors(self, inp: Inputs, chain: Chain) -> Block:
        J = chain.jacobian(inp.column("joints"))
        s = np.sign(approach(inp.column("joints")))
        A = J * (0.5 * s)[:, None, :]
        dof = J.shape[2]
        return Block(self.name, A, tuple(f"width_q{j + 1}" for j in range(dof)), ("rad",) * dof, nonnegative=True)
