"""The physical error effects, each a small function of the plant state.

Joint-space effects return joint deviations (rad) added to the commanded angles before the
actual (perturbed) kinematics; Cartesian effects return TCP deviations (m).
"""
from __future__ import annotations

import numpy as np

from sim.scenario import Scenario


def geometric_perturbation(scn: Scenario, joint_names: list[str]):
    """Seeded joint-origin shifts, twists and joint zero offsets of the geometric effect.

    Parameters
    ----------
    scn : Scenario
    joint_names : list of str

    Returns
    -------
    xyz : dict
        Joint name (and ``tcp_fixed``) -> (3,) m.
    rpy : dict
        Joint name (and ``tcp_fixed``) -> (3,) rad.
    offsets : ndarray
        (n_joints,) rad.
    """
    g = scn.effects.geometric
    rng = np.random.default_rng([scn.seed, 101])
    names = joint_names + ["tcp_fixed"]
    xyz = {n: rng.normal(0, g.link_sigma_m, 3) for n in names}
    rpy = {n: rng.normal(0, g.twist_sigma_rad, 3) for n in names}
    offsets = rng.normal(0, g.joint_offset_sigma_rad, len(joint_names))
    return xyz, rpy, offsets


def compliance(scn: Scenario, holding_torque: np.ndarray) -> np.ndarray:
    # A torsional spring per joint: gravity deflects the joint by -tau_hold / k.
    """Joint deflections of a torsional spring per joint: -holding torque / stiffness.

    Parameters
    ----------
    scn : Scenario
    holding_torque : ndarray
        (n_joints,) N m.

    Returns
    -------
    ndarray
        (n_joints,) rad.
    """
    return -holding_torque / np.asarray(scn.effects.compliance.stiffness_nm_per_rad)


def gear(scn: Scenario, q: np.ndarray) -> np.ndarray:
    """Gear transmission error: amplitude * sin(harmonic * q + phase) per joint.

    Parameters
    ----------
    scn : Scenario
    q : ndarray
        (n_joints,) rad, commanded.

    Returns
    -------
    ndarray
        (n_joints,) rad.
    """
    e = scn.effects.gear
    return np.asarray(e.amplitude_rad) * np.sin(np.asarray(e.harmonic) * q + np.asarray(e.phase_rad))


def backlash(scn: Scenario, approach_sign: np.ndarray) -> np.ndarray:
    # The load side stays behind the motor by half the play, opposite to the motion.
    """Backlash: the load side stays behind the motor by half the play, opposite to the motion.

    Parameters
    ----------
    scn : Scenario
    approach_sign : ndarray
        (n_joints,) -1, 0 or +1, each joint's direction of approach.

    Returns
    -------
    ndarray
        (n_joints,) rad.
    """
    return -0.5 * np.asarray(scn.effects.backlash.width_rad) * approach_sign


def drift(scn: Scenario, t: float) -> np.ndarray:
    """Joint drift: the scenario's rates times the elapsed time.

    Parameters
    ----------
    scn : Scenario
    t : float
        s, simulated clock.

    Returns
    -------
    ndarray
        (n_joints,) rad.
    """
    return np.asarray(scn.effects.drift.joint_rate_rad_per_h) * (t / 3600.0)


def thermal_scale(scn: Scenario, temperature_c: float) -> float:
    """The arm's relative expansion: expansion_per_k * (temperature - reference).

    Parameters
    ----------
    scn : Scenario
    temperature_c : float
        The structure's temperature (deg C).

    Returns
    -------
    float
        Dimensionless scale; positions grow by (1 + scale) about the base.
    """
    th = scn.effects.thermal
    return th.expansion_per_k * (temperature_c - th.reference_c)


def lag_step(ts0: float, air0: float, air1: float, dt: float, tau: float) -> float:
    """The structure's temperature after dt of dTs/dt = (T - Ts)/tau, the air going linearly
    from air0 to air1 (exact for that).

    Parameters
    ----------
    ts0 : float
        The structure's temperature at the start (deg C).
    air0, air1 : float
        The air's temperature at the start and the end (deg C).
    dt : float
        s; <= 0 returns ``ts0``.
    tau : float
        The lag's time constant (s).

    Returns
    -------
    float
        deg C.
    """
    if dt <= 0:
        return ts0
    a = np.exp(-dt / tau)
    ramp = (air1 - air0) / dt * tau
    return float(air1 - ramp + (ts0 - air0 + ramp) * a)


def dynamic(scn: Scenario, speed: float, approach_dir: np.ndarray) -> np.ndarray:
    """Dynamic error at the stop: lag_s * v along the approach plus sag_s * v along -z.

    Parameters
    ----------
    scn : Scenario
    speed : float
        m/s.
    approach_dir : ndarray
        (3,) unit vector of the last motion.

    Returns
    -------
    ndarray
        (3,) m.
    """
    d = scn.effects.dynamic
    return speed * (d.lag_s * approach_dir + d.sag_s * np.array([0.0, 0.0, -1.0]))
