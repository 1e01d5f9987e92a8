"""`thermal`: expansion of the structure with temperature, the structure lagging the air."""
from __future__ import annotations

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs

REFERENCE_TEMPERATURE_C = 20.0  # ISO 1: the reference temperature of dimensional metrology
# The structure's time constants the fit profiles over (s): 0 (it follows the logged air
# temperature at once) and 1 min .. 8 h (warm-up of an industrial arm: tens of minutes).
LAG_GRID_S = np.concatenate([[0.0], np.geomspace(60.0, 8 * 3600.0, 36)])


def lagged(t: np.ndarray, temperature: np.ndarray, tau: float, start: float | None = None) -> np.ndarray:
    """The structure's temperature T_s following the logged temperature T through a first-order
    lag dT_s/dt = (T - T_s) / tau, exact for T linear between samples:

        T_s(t1) = T1 - s tau + (T_s(t0) - T0 + s tau) exp(-(t1 - t0) / tau),  s = (T1 - T0)/(t1 - t0)

    starting at `start` (default: in equilibrium with the first row). tau = 0: T_s = T.

    Parameters
    ----------
    t : ndarray
        (n,) time, s, in order.
    temperature : ndarray
        (n,) logged temperature.
    tau : float
        Time constant, s.
    start : float, optional
        T_s at the first row.

    Returns
    -------
    ndarray
        (n,).
    """
    T = np.asarray(temperature, dtype=float)
    if tau <= 0 or len(T) == 0:
        return T.copy()
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)
    a = np.exp(-np.maximum(dt, 0.0) / tau)
    # The slope's contribution s tau (1 - a), with s tau -> 0 for coincident rows.
    with np.errstate(divide="ignore", invalid="ignore"):
        ramp = np.where(dt > 0, np.diff(T) / np.where(dt > 0, dt, 1.0) * tau * (1 - a), 0.0)
    drive = T[1:] - a * T[:-1] - ramp  # T_s(t1) = a T_s(t0) + drive
    out = np.empty_like(T)
    out[0] = T[0] if start is None else start
    ts = out[0]
    for k in range(len(drive)):  # a recursion with varying coefficients: no vector form that stays stable
        ts = a[k] * ts + drive[k]
        out[k + 1] = ts
    return out


class Thermal(Effect):
    """Expansion about the base: actual = (1 + alpha dT) p, so e = -alpha dT p, with dT the
    structure's temperature from the ISO 1 reference 20 C (a fixed reference, so a saved model
    means the same on new data; the geometric terms or the GP take up the part at the data's mean
    temperature). The structure follows the logged temperature with the time constant `lag_s`
    (`lagged`), which the fit estimates by profile likelihood over LAG_GRID_S when the data have
    a time column (`HybridModel`); 0 s is the air temperature as logged. When the robot config
    lists `thermal_links`, each group of links gets its own coefficient (`regressors`)."""

    name = "thermal"
    columns = ("temperature",)
    needs_chain = False
    factor = "the temperature, growing with distance from the base"
    varies_with = ("temperature",)
    uses_chain = True  # per link when the robot config lists thermal_links
    hyper = {"lag_s": LAG_GRID_S}
    hyper_units = {"lag_s": "s"}
    hyper_columns = ("t",)

    def reads(self, chain: Chain | None) -> tuple[str, ...]:
        """The columns it reads: with the chain's thermal links, the joint angles too.

        Parameters
        ----------
        chain : Chain or None
            The robot's kinematic chain.

        Returns
        -------
        tuple of str
        """
        # per link, the links' directions come from the joint angles
        return self.columns + ("joints",) if chain is not None and chain.thermal_links else self.columns

    def regressors(self, inp: Inputs, chain: Chain | None = None, lag_s: float = 0.0) -> Block:
        """The block: expansion with the (lagged) structure temperature, uniform or per link.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain, optional
            With `thermal_links`, one coefficient per link group.
        lag_s : float, optional
            Lag of the structure's temperature behind the logged one, s.

        Returns
        -------
        Block
            Parameters alpha (1/K), or one per link group.
        """
        T = self.structure_temperature(inp, lag_s)
        dT = T - REFERENCE_TEMPERATURE_C
        if chain is None or not chain.thermal_links:
            A = (-dT[:, None] * inp.commanded)[:, :, None]
            return Block(self.name, A, ("alpha",), ("1/K",))
        # Per link: link j grows by alpha_j dT along itself (Chain.segments), so the TCP moves by
        # the sum over links, e = -sum_j alpha_j dT s_j. With every link in one group this is the
        # uniform term about the robot frame's origin.
        seg = chain.segments(inp.column("joints"))
        A = np.stack([-dT[:, None] * seg[:, list(g)].sum(axis=1) for g in chain.thermal_links], axis=2)
        names = tuple(f"alpha_link{g[0]}" if len(g) == 1 else "alpha_links" + "_".join(map(str, g))
                      for g in chain.thermal_links)
        return Block(self.name, A, names, ("1/K",) * len(names))

    @staticmethod
    def structure_temperature(inp: Inputs, lag_s: float) -> np.ndarray:
        """The structure's temperature of each row: given (`Inputs.structure_temperature`, a
        deployed twin's running state), else the logged temperature lagged by lag_s (needs t).

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        lag_s : float
            The lag, s.

        Returns
        -------
        ndarray
            (n,), deg C.
        """
        if inp.structure_temperature is not None:
            return inp.structure_temperature
        T = inp.column("temperature")
        if lag_s <= 0:
            return T
        if inp.t is None:
            raise DataError(f"effect 'thermal' with the structure lagging the air by {lag_s:.0f} s needs the "
                            "time column t")
        return lagged(inp.t, T, lag_s)
