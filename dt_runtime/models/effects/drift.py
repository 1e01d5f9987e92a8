"""`drift`: slow change of the joints with time."""
from __future__ import annotations

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs

S_PER_H = 3600.0


class Drift(Effect):
    """Slow joint drift: dq_j = r_j t, t in hours from the first row (or `Inputs.t_origin`)."""

    name = "drift"
    columns = ("joints", "t")
    factor = "the time since the start of the data"
    varies_with = ("time",)

    def regressors(self, inp: Inputs, chain: Chain) -> Block:
        """The block: each joint's drift rate times the hours since the time origin, through the Jacobian.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain
            The robot's kinematic chain.

        Returns
        -------
        Block
            Parameters rate_q1..N, rad/h.
        """
        J = chain.jacobian(inp.column("joints"))
        t = inp.column("t")
        t0 = inp.t_origin if inp.t_origin is not None else t[0]
        h = (t - t0)[:, None, None] / S_PER_H
        dof = J.shape[2]
        return Block(self.name, -J * h, tuple(f"rate_q{j + 1}" for j in range(dof)), ("rad/h",) * dof)
