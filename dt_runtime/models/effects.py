"""Physical effect terms of the hybrid error model: each effect is linear in parameters that
mean something physically (joint offsets in rad, stiffness in N m/rad, backlash width in rad,
expansion coefficient in 1/K, lag in s, drift in rad/h).

An effect builds, for every row, a 3 x p regressor block A with e = commanded - measured
= A theta. Joint-space effects act through the TCP Jacobian J of the nominal kinematics: the
arm reaches fk(q + dq) ~ fk(q) + J dq, so a joint deviation dq contributes e = -J dq.
Names are the DESIGN.md contract: geometric, compliance, gear, backlash, thermal, dynamic, drift.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.geometry import skew
from dt_runtime.frames.kinematics import Chain

EFFECT_NAMES = ("geometric", "compliance", "gear", "backlash", "thermal", "dynamic", "drift")
GRAVITY = 9.80665


@dataclass(frozen=True)
class Inputs:
    """What the effect terms may use; SI units, rows in time order."""

    commanded: np.ndarray  # (n,3) m
    joints: np.ndarray | None = None  # (n,dof) rad
    speed: np.ndarray | None = None  # (n,) m/s
    temperature: np.ndarray | None = None  # (n,) deg C
    payload: np.ndarray | None = None  # (n,) kg
    t: np.ndarray | None = None  # (n,) s

    @property
    def n(self) -> int:
        return len(self.commanded)

    @classmethod
    def of(cls, ds) -> "Inputs":
        """The columns of a `dt_runtime.measurements.dataset.Dataset` the effect terms may use."""
        return cls(commanded=ds.commanded, joints=ds.joints, speed=ds.speed,
                   temperature=ds.temperature, payload=ds.payload, t=ds.t)

    def subset(self, mask) -> "Inputs":
        return Inputs(**{f: (None if getattr(self, f) is None else getattr(self, f)[mask])
                         for f in ("commanded", "joints", "speed", "temperature", "payload", "t")})


@dataclass(frozen=True)
class Block:
    effect: str
    A: np.ndarray  # (n, 3, p)
    names: tuple[str, ...]
    units: tuple[str, ...]
    # Reported quantity per parameter: identity, or 1/x (compliance -> stiffness).
    report: str = "identity"


def _need(inp: Inputs, effect: str, *cols: str) -> None:
    missing = [c for c in cols if getattr(inp, c) is None]
    if missing:
        raise DataError(f"effect '{effect}' needs the column(s) {', '.join(missing)}, "
                        f"which the data does not have")


def _approach(x: np.ndarray) -> np.ndarray:
    """Direction of approach of each row from the previous row (first row: from the second)."""
    d = np.zeros_like(x)
    d[1:] = x[1:] - x[:-1]
    d[0] = d[1] if len(x) > 1 else 0.0
    return d


def geometric(inp: Inputs, chain: Chain) -> Block:
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
    _need(inp, "geometric", "joints")
    pos, rot, T = chain.frames(inp.joints)
    J = chain.jacobian(inp.joints)
    n, _, dof = J.shape
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
    return Block("geometric", np.concatenate(blocks, axis=2), tuple(names), tuple(units))


def compliance(inp: Inputs, chain: Chain) -> Block:
    """Joint compliance c_j = 1/k_j under the payload's torque: dq_j = -tau_j c_j.

    The holding torque of a payload m at the TCP is tau = J^T (0, 0, m g). The arm's own
    weight gives a torque that depends on q only: the position/joint GP absorbs it, while the
    payload-driven part is what a model without payload cannot know.
    """
    _need(inp, "compliance", "joints", "payload")
    J = chain.jacobian(inp.joints)
    tau = J[:, 2, :] * (inp.payload[:, None] * GRAVITY)  # (n, dof) N m
    A = J * tau[:, None, :]  # e = -J dq = J diag(tau) c
    dof = J.shape[2]
    return Block("compliance", A, tuple(f"compliance_q{j + 1}" for j in range(dof)),
                 ("rad/(N m)",) * dof, report="inverse")


def gear(inp: Inputs, chain: Chain) -> Block:
    """Transmission error periodic in joint angle: dq_j = sum_h a sin(h q_j) + b cos(h q_j),
    over the robot model's candidate harmonics (`gear_harmonics` in its config)."""
    _need(inp, "gear", "joints")
    J = chain.jacobian(inp.joints)
    q = inp.joints
    cols, names = [], []
    for j in range(J.shape[2]):
        for h in chain.gear_harmonics:
            for fn, lab in ((np.sin, "sin"), (np.cos, "cos")):
                cols.append(-J[:, :, j] * fn(h * q[:, j])[:, None])
                names.append(f"q{j + 1}_{lab}{h}")
    return Block("gear", np.stack(cols, axis=2), tuple(names), ("rad",) * len(names))


def backlash(inp: Inputs, chain: Chain) -> Block:
    """Half the play against the direction of approach: dq_j = -(w_j / 2) sign(dq_j)."""
    _need(inp, "backlash", "joints")
    J = chain.jacobian(inp.joints)
    s = np.sign(_approach(inp.joints))
    A = J * (0.5 * s)[:, None, :]
    dof = J.shape[2]
    return Block("backlash", A, tuple(f"width_q{j + 1}" for j in range(dof)), ("rad",) * dof)


REFERENCE_TEMPERATURE_C = 20.0  # ISO 1: the reference temperature of dimensional metrology


def thermal(inp: Inputs, chain: Chain | None = None) -> Block:
    """Expansion about the base: actual = (1 + alpha dT) p, so e = -alpha dT p, with dT from
    the ISO 1 reference 20 C (a fixed reference, so a saved model means the same on new data;
    the geometric terms or the GP take up the part at the data's mean temperature)."""
    _need(inp, "thermal", "temperature")
    dT = inp.temperature - REFERENCE_TEMPERATURE_C
    A = (-dT[:, None] * inp.commanded)[:, :, None]
    return Block("thermal", A, ("alpha",), ("1/K",))


def dynamic(inp: Inputs, chain: Chain | None = None) -> Block:
    """Speed-dependent error at the stop: lag along the approach and sag along -z, both ~ v."""
    _need(inp, "dynamic", "speed")
    d = _approach(inp.commanded)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    u = np.divide(d, norm, out=np.zeros_like(d), where=norm > 0)
    v = inp.speed[:, None]
    lag = -(v * u)
    sag = np.zeros_like(lag)
    sag[:, 2] = v[:, 0]  # actual lower by sag*v -> e_z = +sag*v
    return Block("dynamic", np.stack([lag, sag], axis=2), ("lag", "sag"), ("s", "s"))


def drift(inp: Inputs, chain: Chain) -> Block:
    """Slow joint drift: dq_j = r_j t."""
    _need(inp, "drift", "joints", "t")
    J = chain.jacobian(inp.joints)
    h = (inp.t - inp.t[0])[:, None, None] / 3600.0
    dof = J.shape[2]
    return Block("drift", -J * h, tuple(f"rate_q{j + 1}" for j in range(dof)), ("rad/h",) * dof)


BUILDERS = {"geometric": geometric, "compliance": compliance, "gear": gear, "backlash": backlash,
            "thermal": thermal, "dynamic": dynamic, "drift": drift}


def build(effect: str, inp: Inputs, chain: Chain | None) -> Block:
    if effect not in BUILDERS:
        raise DataError(f"unknown effect '{effect}'; known: {', '.join(EFFECT_NAMES)}")
    if chain is None and effect not in ("thermal", "dynamic"):
        raise DataError(f"effect '{effect}' needs the robot's kinematic model (--robot)")
    return BUILDERS[effect](inp, chain)


def available(inp: Inputs, chain: Chain | None) -> list[str]:
    """Effects whose regressors the data's columns (and the kinematic model) allow."""
    need = {"geometric": ("joints",), "compliance": ("joints", "payload"), "gear": ("joints",),
            "backlash": ("joints",), "thermal": ("temperature",), "dynamic": ("speed",),
            "drift": ("joints", "t")}
    out = []
    for e in EFFECT_NAMES:
        if all(getattr(inp, c) is not None for c in need[e]) and (chain is not None or e in ("thermal", "dynamic")):
            out.append(e)
    return out
