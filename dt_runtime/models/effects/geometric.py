"""`geometric`: joint zero offsets and small errors of every joint frame and of the tool."""
from __future__ import annotations

import numpy as np

from dt_kernel.geometry import skew
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs


class Geometric(Effect):
    """Joint zero offsets (rad), small translations (m) and rotations (rad) of every joint
    frame, expressed in that frame's own axes (link length and twist errors), and the tool's
    translation in the flange frame.

    A frame j shifted by d (frame axes) moves the TCP by R_j d; rotated by w (frame axes) it
    moves the TCP by (R_j w) x (p_tcp - p_j). The set is deliberately complete, hence rank
    deficient (some parameters act alike for a single TCP point); the hybrid model's ridge
    penalty picks the smallest parameters that explain the data. Frame 1 (the base) is kept:
    a registration made at one place in the workspace leaves a small rigid misalignment that
    only these terms (or the GP) can take up.
    """

    name = "geometric"
    columns = ("joints",)
    factor = "the joint configuration (joint zero offsets and link errors)"
    varies_with = ()

    def regressors(self, inp: Inputs, chain: Chain) -> Block:
        """The block: joint offsets, each joint frame's translation and rotation errors, the tool offset.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain
            The robot's kinematic chain.

        Returns
        -------
        Block
            Parameters offset_q<j> (rad), frame<j>_d{x,y,z} (m), frame<j>_r{x,y,z} (rad), tool_d{x,y,z} (m).
        """
        pos, rot, T = chain.frames(inp.column("joints"))
        J = np.cross(chain.world_axes(rot), T[:, None, :3, 3] - pos).transpose(0, 2, 1)  # Chain.jacobian, same frames
        dof = J.shape[2]
        p = T[:, :3, 3]
        blocks = [-J]
        names = [f"offset_q{j + 1}" for j in range(dof)]
        units = ["rad"] * dof
        for j in range(dof):
            R = rot[:, j]
            blocks.append(-R)  # translation d_j in frame axes
            lever = p - pos[:, j]
            # (R w) x lever = -[lever]x R w
            blocks.append(np.einsum("nab,nbc->nac", skew(lever), R))
            names += [f"frame{j + 1}_d{a}" for a in "xyz"] + [f"frame{j + 1}_r{a}" for a in "xyz"]
            units += ["m"] * 3 + ["rad"] * 3
        blocks.append(-T[:, :3, :3])  # tool (TCP) offset error, flange axes
        names += [f"tool_d{a}" for a in "xyz"]
        units += ["m"] * 3
        return Block(self.name, np.concatenate(blocks, axis=2), tuple(names), tuple(units))
