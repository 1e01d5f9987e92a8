"""`thermal`: expansion of the structure with temperature."""
from __future__ import annotations

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs

REFERENCE_TEMPERATURE_C = 20.0  # ISO 1: the reference temperature of dimensional metrology


class Thermal(Effect):
    """Expansion about the base: actual = (1 + alpha dT) p, so e = -alpha dT p, with dT from
    the ISO 1 reference 20 C (a fixed reference, so a saved model means the same on new data;
    the geometric terms or the GP take up the part at the data's mean temperature)."""

    name = "thermal"
    columns = ("temperature",)
    needs_chain = False
    factor = "the temperature, growing with distance from the base"

    def regressors(self, inp: Inputs, chain: Chain | None = None) -> Block:
        dT = inp.column("temperature") - REFERENCE_TEMPERATURE_C
        A = (-dT[:, None] * inp.commanded)[:, :, None]
        return Block(self.name, A, ("alpha",), ("1/K",))
