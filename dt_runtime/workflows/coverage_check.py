"""Does the stated per-position uncertainty cover the truth, inside the calibrated volume and
outside it? A check only a simulator can make: distinct random targets, commanded with the
twin's correction, scored against where the arm truly went.

Inside targets are drawn uniformly in the convex hull of the DOE; outside targets in a band of
signed distance (e.g. 50-150 mm) beyond it, by the hull's facet distance (`CalibratedVolume`).
Every target is checked for reachability before anything moves; unreachable draws are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import UnreachableError
from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.common.progress import Progress
from dt_runtime.frames.volume import CalibratedVolume
from dt_runtime.measurements.plans import PlanRow
from dt_runtime.metrology.stats import rms3
from dt_runtime.models.effects import Inputs
from dt_runtime.twin.twin import Correction, Twin
from dt_runtime.workflows.campaign import Instruments, run_rows


@dataclass(frozen=True)
class CoverageCheck:
    """Corrected commands scored against the simulator's truth (`run_check`).

    Attributes
    ----------
    target : ndarray
        (n, 3) m, robot frame.
    command : ndarray
        (n, 3) m, the corrected commands sent.
    U : ndarray
        (n, 3) m, stated expanded uncertainty (95 %) of each corrected position.
    error : ndarray
        (n, 3) m, true error in GL: target - where the arm truly went.
    distance : ndarray
        (n,) m, signed distance of the command to the DOE hull.
    inside : ndarray
        (n,) bool, the twin's calibrated-volume flag.
    requested : int or None
        The number of targets the check asked for (None: as many as it has).
    joints : ndarray or None
        (n, dof) rad, where the arm stood at each position.
    t, temperature : ndarray or None
        (n,) s and deg C.
    """

    target: np.ndarray  # (n,3) m, robot frame
    command: np.ndarray  # (n,3) m, the corrected commands sent
    U: np.ndarray  # (n,3) m, stated expanded uncertainty (95 %) of each corrected position
    error: np.ndarray  # (n,3) m, true error in GL: target - where the arm truly went
    distance: np.ndarray  # (n,) m, signed distance of the command to the DOE hull
    inside: np.ndarray  # (n,) bool, the twin's flag
    requested: int | None = None  # the number of targets the check asked for (None: as many as it has)
    joints: np.ndarray | None = None  # (n,dof) rad, where the arm stood at each position
    t: np.ndarray | None = None  # (n,) s
    temperature: np.ndarray | None = None  # (n,) deg C

    @property
    def n(self) -> int:
        """Number of positions."""
        return len(self.target)

    def head(self, n: int) -> CoverageCheck:
        """The first n positions (the check states coverage over a fixed number of targets); when
        fewer were reached, all of them, with the number asked for kept in `requested`.

        Parameters
        ----------
        n : int
            The number of targets the check states its coverage over.

        Returns
        -------
        CoverageCheck
        """
        def cut(a):
            return None if a is None else a[:n]

        return CoverageCheck(self.target[:n], self.command[:n], self.U[:n], self.error[:n], self.distance[:n],
                             self.inside[:n], n, cut(self.joints), cut(self.t), cut(self.temperature))

    def conditions(self) -> Inputs:
        """The commanded targets and what the arm and the cell were at (the validity check's input)."""
        return Inputs(commanded=self.target, joints=self.joints, t=self.t, temperature=self.temperature)

    def coverage(self) -> dict[str, float]:
        """Per axis, the fraction of positions whose true error lies within +/- U."""
        ok = np.abs(self.error) <= self.U
        return {ax: float(ok[:, k].mean()) for k, ax in enumerate(AXES)}

    def summary(self) -> dict:
        """The summary's `coverage_check` entry: `n`, `n_requested` (when set), `coverage_95`,
        `mean_U_mm`, `true_rms_mm`, `distance_mm` (min, max) and `flagged_inside_fraction`."""
        return {"n": self.n, **({"n_requested": self.requested} if self.requested is not None else {}),
                "coverage_95": self.coverage(),
                "mean_U_mm": [round(float(x) * MM_PER_M, 4) for x in self.U.mean(axis=0)],
                "true_rms_mm": round(rms3(self.error) * MM_PER_M, 4),
                "distance_mm": [round(float(self.distance.min()) * MM_PER_M, 1),
                                round(float(self.distance.max()) * MM_PER_M, 1)],
                "flagged_inside_fraction": float(self.inside.mean())}


def sample_targets(volume: CalibratedVolume, doe_points: np.ndarray, n: int, band_m: tuple[float, float],
                   world, rng: np.random.Generator, max_draws: int = 200_000) -> np.ndarray:
    """n reachable targets whose signed distance to the hull lies in `band_m` (m; (-inf, 0) for
    inside), drawn uniformly in the DOE's bounding box widened by the band's far edge.

    Parameters
    ----------
    volume : CalibratedVolume
        The DOE hull.
    doe_points : ndarray
        (m, 3) m, the DOE's points (their bounding box).
    n : int
        How many targets.
    band_m : tuple of float
        (low, high) signed distance to the hull, m.
    world : SimWorld or None
        Drops the unreachable draws (None: none dropped).
    rng : numpy.random.Generator
        The draws' generator.
    max_draws : int
        Give up after this many draws.

    Returns
    -------
    ndarray
        (n, 3) m, robot frame.

    Raises
    ------
    UnreachableError
        Fewer than n reachable targets in the band after `max_draws` draws.
    """
    lo, hi = band_m
    pad = max(hi, 0.0)
    box_lo, box_hi = doe_points.min(axis=0) - pad, doe_points.max(axis=0) + pad
    out: list[np.ndarray] = []
    drawn = 0
    while len(out) < n and drawn < max_draws:
        P = rng.uniform(box_lo, box_hi, (4 * n, 3))
        drawn += len(P)
        d = volume.distance(P)
        P = P[(d >= lo) & (d <= hi)]
        if world is not None and len(P):
            bad = {i for i, _ in world.unreachable(P)}
            P = P[[i not in bad for i in range(len(P))]]
        out.extend(P)
    if len(out) < n:
        raise UnreachableError(f"only {len(out)} reachable targets in the band {band_m} m after {drawn} draws")
    return np.array(out[:n])


def run_check(inst: Instruments, twin: Twin, targets: np.ndarray, speeds: np.ndarray,
              progress: Progress | None = None, label: str = "coverage check") -> CoverageCheck:
    """Command every target corrected, at its speed fraction, and score against the truth.
    Only the robot and the truth are needed: the camera is not read.

    Parameters
    ----------
    inst : Instruments
        The simulated cell (its `world` gives the truth).
    twin : Twin
        The twin whose correction and U are checked.
    targets : ndarray
        (n, 3) m, robot frame.
    speeds : ndarray
        (n,) speed fractions of `inst.max_speed`.
    progress : Progress or None
        Where progress goes.
    label : str
        The run's name in progress and refusals.

    Returns
    -------
    CoverageCheck
        Over the targets reached (a command the arm cannot reach from where it stands is skipped).
    """
    rows = [PlanRow("check", i, 0, t, float(s)) for i, (t, s) in enumerate(zip(targets, speeds))]
    cs: list[Correction] = []

    def command(target: np.ndarray, v: float, cond) -> np.ndarray:
        cs.append(twin.correct(target, v, cond))
        return cs[-1].command

    data = run_rows(Instruments(inst.robot, inst.tracker, None, world=inst.world, max_speed=inst.max_speed),
                    rows, progress, label, command=command, skip_unreachable=True)
    assert data.truth_lt is not None, "the coverage check needs the simulator's truth"
    # A command the arm cannot reach from where it stands is skipped (its row stays NaN).
    ok = np.all(np.isfinite(data.truth_lt), axis=1)
    # True error in GL (the frame the tracker realises): the intended target vs where the arm went.
    err = twin.T_rdk.apply(data.target[ok]) - twin.T_lt.apply(data.truth_lt[ok])
    return CoverageCheck(data.target[ok], np.array([c.command for c in cs])[ok], np.array([c.U for c in cs])[ok],
                         err, np.array([c.distance_m for c in cs])[ok], np.array([c.inside for c in cs])[ok],
                         joints=data.q[ok], t=data.t[ok], temperature=data.temperature[ok])
