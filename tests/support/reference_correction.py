"""The correction law written plainly, as the paper states it: the fixed point c - e_hat(c, v) =
target on the twin's own map predictor (its `Inputs` and `Chain.ik`), then Eq. 11's labelled budget at
c, its U times the twin's conformal factor. The tests hold `twin.corrector.Corrector` (the one law,
precomputed for speed) to these numbers and `benchmarks.setpoint` uses it as its baseline."""
from __future__ import annotations

import numpy as np

from dt_runtime.twin.conditions import Conditions, command_inputs
from dt_runtime.twin.twin import Correction, Twin


def _lt(twin: Twin, predictor, chain, c: np.ndarray, v: float, cond: Conditions | None, q_seed=None):
    """e_LT_hat at c (GL axes), its std, and c's joints (when the map reads them)."""
    if predictor.plain:
        m, s = predictor.gp_only(np.array([c[0], c[1], c[2], v]))
        return m, s, None
    inp, q = command_inputs(c, v, predictor.needs, cond, chain, q_seed)
    m, s = predictor(inp)
    return m, s, q


class ReferenceCorrector:
    """`correct(target, v, cond) -> Correction` the plain way (its own map predictor)."""

    def __init__(self, twin: Twin, iters: int = 6, tol: float = 1e-8):
        self.twin, self.iters, self.tol = twin, iters, tol
        self._p = twin.e_lt.predictor()
        self._chain = twin.e_lt.chain() if "joints" in self._p.needs else None
        self._Rt = twin.T_rdk.R.T

    def correct(self, target: np.ndarray, v: float, cond: Conditions | None = None) -> Correction:
        tw, target = self.twin, np.asarray(target, dtype=float)
        m, s, q = _lt(tw, self._p, self._chain, target, v, cond)
        c = target + self._Rt @ m
        for _ in range(self.iters):
            m, s, q = _lt(tw, self._p, self._chain, c, v, cond, q)  # the IK starts from the last solution
            c_new = target + self._Rt @ m
            done = np.max(np.abs(c_new - c)) < self.tol
            c = c_new
            if done:
                break
        dist = tw.distance(c)
        b = tw.tcp_budget(c, v, dist, sigma=s)
        U = tw.conformal.factor * (b.expanded() if b is not None else tw.uncertainty.tcp_c.U)
        inside = tw.volume is None or dist <= tw.volume.margin_m
        return Correction(target, c, U, bool(inside), dist, b)
