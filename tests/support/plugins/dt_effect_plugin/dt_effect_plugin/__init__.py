"""A third party's effect: a wooden or polymer fixture under the part swells with the hall's
relative humidity, lifting the part along z by a length per % (m/%). Published through the
entry point group `cobot_dt.effects` (see pyproject.toml); the twin then tests it in
`dt diagnose` and fits it with `dt fit --effects ...,swelling` like a catalogue effect."""
from __future__ import annotations

import numpy as np

from dt_runtime.models.effects import Block, Effect, Inputs

REFERENCE_PERCENT = 45.0


class Swelling(Effect):
    name = "swelling"
    columns = ("humidity",)
    needs_chain = False
    factor = "the relative humidity, along z (the fixture swelling)"

    def regressors(self, inp: Inputs, chain) -> Block:
        A = np.zeros((inp.n, 3, 1))
        # e = commanded - measured: the part (and the measured TCP on it) rises, e_z falls.
        A[:, 2, 0] = -(inp.column("humidity") - REFERENCE_PERCENT)
        return Block(self.name, A, ("lift_per_percent",), ("m/%",))
