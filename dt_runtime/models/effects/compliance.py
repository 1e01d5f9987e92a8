"""`compliance`: joint deflection under the payload's torque."""
from __future__ import annotations

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs

GRAVITY = 9.80665  # m/s^2, standard gravity


class Compliance(Effect):
    """Joint compliance c_j = 1/k_j under the payload's torque: dq_j = -tau_j c_j.

    The holding torque of a payload m at the TCP is tau = J^T (0, 0, m g). The arm's own
    weight gives a torque that depends on q only: the position/joint GP absorbs it, while the
    payload-driven part is what a model without payload cannot know. Reported as stiffness
    k_j = 1/c_j (N m/rad)."""

    name = "compliance"
    columns = ("joints", "payload")
    factor = "the payload torque on the joints"
    varies_with = ("payload",)

    def regressors(self, inp: Inputs, chain: Chain) -> Block:
        """The block: each joint's compliance times the payload's gravity torque, through the Jacobian.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain
            The robot's kinematic chain.

        Returns
        -------
        Block
            Parameters compliance_q1..N, rad/(N m), reported as stiffness (1/x), non-negative.
        """
        J = chain.jacobian(inp.column("joints"))
        tau = J[:, 2, :] * (inp.column("payload")[:, None] * GRAVITY)  # (n, dof) N m
        A = J * tau[:, None, :]  # e = -J dq = J diag(tau) c
        dof = J.shape[2]
        return Block(self.name, A, tuple(f"compliance_q{j + 1}" for j in range(dof)),
                     ("rad/(N m)",) * dof, report="inverse", nonnegative=True)
