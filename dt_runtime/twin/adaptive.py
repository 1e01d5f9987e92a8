"""Adaptive conformal scale of the stated U in service: coverage that holds through slow drift.

Each monitored reading of a corrected position's error (the tracker's, or the camera's) says
whether the stated U covered it; `AdaptiveCoverage` turns that stream into a scale per GL axis by
adaptive conformal inference (Gibbs & Candès 2021) on the log of the scale. The daemon feeds it
every Eq. 17 reading and states the scaled U (docs/service.md, "The stated U in service"); Eq. 17
itself keeps the calibrated U, so the scale cannot absorb a fault.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dt_kernel.errors import ConfigError

ALPHA = 0.05  # the 95 % U
WARN_SCALE = 1.5  # a stated U grown by half: the readings no longer agree with the calibration
GAMMA = 0.05  # step per reading on log(scale)
BOUNDS = (1.0, 20.0)  # the scale never goes below the calibrated U, nor above 20 times it


@dataclass
class AdaptiveCoverage:
    """Adaptive conformal scale of a stated U, per GL axis.

    The miss indicator err_t = 1{|e_t| > s_t U_t} drives log s_{t+1} = log s_t + gamma (err_t - alpha):
    Gibbs & Candès' alpha_{t+1} = alpha_t + gamma (alpha - err_t) written on the log of the scale
    (the quantile-tracking form of Angelopoulos, Candès & Tibshirani 2023). On the alpha form the
    scale is a quantile function of alpha_t, steep where the needed alpha_t is below one step, so U
    would jump between extremes; here it moves by a few per cent per reading. Summing the update
    over any W readings: misses / W = alpha + (log s_end - log s_start) / (gamma W), exactly while
    the scale stays inside its bounds (at the floor: fewer misses).

    Feeding it: for each reading of a corrected position with a measured error e (m, GL axes) and
    the U the twin stated for it, `observe(e, U)` (or `update(|e| <= scale U)`); state `stated(U)`
    from then on; persist `to_dict()` with the service's state. Step `GAMMA` = 0.05 per reading: the
    scale grows 5 % per miss and shrinks 0.25 % per covered reading at alpha = 0.05.

    Parameters
    ----------
    alpha : float
        Target miss rate (0.05 for a 95 % U).
    gamma : float
        Step on log(scale) per reading (> 0).
    bounds : tuple of float
        (lowest, highest) scale; the lowest 1.0 keeps at least the calibrated U.
    scale : ndarray
        (3,) the starting scale (default 1: the U as calibrated).

    Raises
    ------
    ConfigError
        alpha not in (0, 1), gamma <= 0, or bounds not 0 < lowest <= highest (finite).
    """

    alpha: float = ALPHA
    gamma: float = GAMMA
    bounds: tuple[float, float] = BOUNDS
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    n: int = 0  # readings seen
    misses: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=int))  # per axis, all readings

    def __post_init__(self):
        lo, hi = self.bounds
        if not 0 < self.alpha < 1:
            raise ConfigError("AdaptiveCoverage", "alpha", self.alpha, "a miss rate in (0, 1), e.g. 0.05")
        if not (self.gamma > 0 and math.isfinite(self.gamma)):
            raise ConfigError("AdaptiveCoverage", "gamma", self.gamma, "a finite step > 0, e.g. 0.05")
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ConfigError("AdaptiveCoverage", "bounds", self.bounds, "0 < lowest <= highest, finite")
        self.scale = np.clip(np.broadcast_to(np.asarray(self.scale, dtype=float), (3,)).copy(), lo, hi)
        self.misses = np.asarray(self.misses, dtype=int).copy()
        self._log_lo, self._log_hi = math.log(lo), math.log(hi)

    def update(self, covered: np.ndarray) -> np.ndarray:
        """One monitored reading: whether the U stated with the current scale covered its error.

        Parameters
        ----------
        covered : ndarray
            (3,) bool per GL axis: |e| <= scale * U (NaN-free; an axis not measured: pass True
            and it counts as covered, or do not call).

        Returns
        -------
        ndarray
            (3,) the scale for the next reading.
        """
        err = ~np.asarray(covered, dtype=bool)
        self.n += 1
        self.misses += err
        log_s = np.log(self.scale) + self.gamma * (err.astype(float) - self.alpha)
        self.scale = np.exp(np.clip(log_s, self._log_lo, self._log_hi))
        return self.scale

    def observe(self, error: np.ndarray, U: np.ndarray) -> np.ndarray:
        """`update` from a measured error and the U the twin stated for it (before this scale).

        Parameters
        ----------
        error : ndarray
            (3,) m, the measured error of the corrected position, GL axes.
        U : ndarray
            (3,) m, the stated U(TCP_c) there (the twin's, without this scale).

        Returns
        -------
        ndarray
            (3,) the scale for the next reading.
        """
        return self.update(np.abs(np.asarray(error, dtype=float)) <= self.scale * np.asarray(U, dtype=float))

    def stated(self, U: np.ndarray) -> np.ndarray:
        """The U to state now.

        Parameters
        ----------
        U : ndarray
            (3,) m, the twin's stated U at the position.

        Returns
        -------
        ndarray
            (3,) m: the scale times U.
        """
        return self.scale * np.asarray(U, dtype=float)

    def health(self) -> dict[str, Any]:
        """What the service says of it (`.../health` under `stated_u`): the scale per axis, the
        readings and misses it saw, the guarantee, and a warning in words once a scale passes
        `WARN_SCALE`.

        Returns
        -------
        dict
            `scale`, `n`, `miss_rate`, `guarantee`, `warning` (None while every scale is below).
        """
        grown = [f"{a} x{s:.2f}" for a, s in zip("xyz", self.scale) if s >= WARN_SCALE]
        warning = None if not grown else (
            f"the readings need a larger U than the calibration states ({', '.join(grown)}): the cell drifted "
            "from its calibration; run the daily check (dt calibrate --reference FILE --twin DIR) or recalibrate")
        rate = (self.misses / self.n).round(4).tolist() if self.n else [None, None, None]
        return {"scale": self.scale.round(4).tolist(), "n": self.n, "miss_rate": rate,
                "guarantee": f"adaptive conformal (Gibbs & Candes 2021), target miss rate {self.alpha:g}, "
                             f"step {self.gamma:g} on log(scale), bounds {self.bounds[0]:g}-{self.bounds[1]:g}",
                "warning": warning}

    def to_dict(self) -> dict[str, Any]:
        """The state, JSON-ready (to persist with the service's state)."""
        return {"method": "adaptive conformal inference (Gibbs & Candes 2021) on log(scale)", "alpha": self.alpha,
                "gamma": self.gamma, "bounds": list(self.bounds), "scale": self.scale.tolist(), "n": self.n,
                "misses": self.misses.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AdaptiveCoverage:
        """What `to_dict` wrote.

        Parameters
        ----------
        d : dict
            The state.

        Returns
        -------
        AdaptiveCoverage
        """
        return cls(float(d["alpha"]), float(d["gamma"]), (float(d["bounds"][0]), float(d["bounds"][1])),
                   np.asarray(d["scale"], dtype=float), int(d["n"]), np.asarray(d["misses"], dtype=int))
