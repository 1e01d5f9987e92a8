"""The paper's three experiment phases as data (Sect. 2.2), in metres, robot frame.

Registration (three-line method), DOE (62 targets, Fig. 5: `doe_points`) and validation, each
replication in its own random order (`build_plan`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from dt_kernel.config import Frozen, load_yaml

Speed = Field(gt=0, le=1)


class PlanConfig(Frozen):
    """The plan's geometry, speeds (fractions of the maximum) and counts (plan YAML)."""
    seed: int = 1
    center_m: tuple[float, float, float] = (0.9, 0.0, 0.55)  # middle rectangle's centre
    spacing_m: float = Field(0.15, gt=0, le=0.5)
    plane_separation_m: float = Field(0.35, gt=0, le=1.0)
    registration_origin_m: tuple[float, float, float] = (0.9, 0.0, 0.55)
    registration_distances_m: tuple[float, ...] = Field((0.025, 0.05, 0.075, 0.1), max_length=100)
    # Counts are bounded (a typo such as doe_reps: 100000000 would eat memory until killed):
    # the paper's plan is 10 / 9 / 14 x 5; the bounds leave room for any real campaign.
    registration_reps: int = Field(10, ge=2, le=100)
    registration_speed: float = Speed
    doe_speeds: tuple[float, ...] = Field((0.3, 0.6, 0.9), max_length=100)
    doe_reps: int = Field(9, ge=1, le=100)
    validation_points: int = Field(14, ge=1, le=10_000)
    validation_speeds: tuple[float, ...] = Field((0.8, 0.4), max_length=100)
    validation_reps_per_speed: int = Field(5, ge=1, le=100)

    @field_validator("doe_speeds", "validation_speeds")
    @classmethod
    def _speeds(cls, v):
        if not v or any(not (0 < s <= 1) for s in v):
            raise ValueError("speeds are fractions of the maximum speed, each in (0, 1]")
        return v

    @field_validator("registration_distances_m")
    @classmethod
    def _dist(cls, v):
        if len(v) < 2 or any(d <= 0 for d in v):
            raise ValueError("at least two positive distances along each registration line")
        return v


@dataclass(frozen=True)
class PlanRow:
    """One positioning: phase, target point and replication, target (m), speed fraction, and for
    registration the line and distance along it.
    """
    phase: str
    point_id: int
    rep: int
    target: np.ndarray
    speed_frac: float
    axis: str | None = None
    distance: float | None = None


@dataclass(frozen=True)
class Plan:
    """The three phases' positionings, in order, and the distinct DOE and validation targets."""
    registration: list[PlanRow]
    doe: list[PlanRow]
    validation: list[PlanRow]
    doe_points: np.ndarray  # (62, 3) unique DOE targets
    validation_points: np.ndarray

    def all_targets(self) -> np.ndarray:
        """Every positioning's target, phase by phase.

        Returns
        -------
        ndarray
            (n, 3), m.
        """
        return np.array([r.target for r in self.registration + self.doe + self.validation])


def load_plan(path: str | Path) -> PlanConfig:
    """Read a plan YAML.

    Parameters
    ----------
    path : str or Path
        The YAML file.

    Returns
    -------
    PlanConfig

    Raises
    ------
    ConfigError
        Naming the file, key, value and what is allowed.
    """
    return load_yaml(path, PlanConfig)


def _rect_perimeter(a: float, b: float, s: float) -> list[tuple[float, float]]:
    nx, ny = round(a / s), round(b / s)
    pts = {(round(i * s - a / 2, 9), round(j * s - b / 2, 9))
           for i in range(nx + 1) for j in range(ny + 1) if i in (0, nx) or j in (0, ny)}
    return sorted(pts)


def doe_points(cfg: PlanConfig) -> np.ndarray:
    """The 62 DOE targets (Fig. 5) on three horizontal rectangles with ascending areas.

    With the default spacing s = 150 mm and plane separation 350 mm:

    - R1 (top) 300 x 300 mm: the 3 x 3 grid of its sides, with the diagonals' crossing: 9 points;
    - R2 (middle) 600 x 300 mm: its perimeter (12) and the diagonals' crossing: 13;
    - R3 (bottom) 750 x 600 mm: its perimeter (18) and 4 points on each diagonal (at 1/5 ... 4/5
      of its length, about 190 mm apart): 26;
    - 14 points on the lines joining the vertices: the midpoint of each of the four lines
      R1 -> R2 (4), two points at thirds on each of the four lines R2 -> R3 (8), and the two
      midpoints of the vertical line joining the diagonals' crossings of R1, R2 and R3 (2).

    Parameters
    ----------
    cfg : PlanConfig
        The plan's geometry.

    Returns
    -------
    ndarray
        (62, 3), m.
    """
    s, h = cfg.spacing_m, cfg.plane_separation_m
    cx, cy, cz = cfg.center_m
    sizes = [(2 * s, 2 * s), (4 * s, 2 * s), (5 * s, 4 * s)]  # R1, R2, R3
    zs = [cz + h, cz, cz - h]
    pts: list[tuple[float, float, float]] = []
    corners = []
    for k, ((a, b), z) in enumerate(zip(sizes, zs)):
        per = _rect_perimeter(a, b, s)
        pts += [(cx + x, cy + y, z) for x, y in per]
        corners.append([(cx + sx * a / 2, cy + sy * b / 2, z) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        if k < 2:
            pts.append((cx, cy, z))  # diagonals' crossing
        else:
            for c0, c1 in ((corners[k][0], corners[k][2]), (corners[k][1], corners[k][3])):
                for f in (0.2, 0.4, 0.6, 0.8):
                    pts.append(tuple(np.asarray(c0) + f * (np.asarray(c1) - np.asarray(c0))))
    for c1, c2 in zip(corners[0], corners[1]):
        pts.append(tuple((np.asarray(c1) + np.asarray(c2)) / 2))
    for c2, c3 in zip(corners[1], corners[2]):
        for f in (1 / 3, 2 / 3):
            pts.append(tuple(np.asarray(c2) + f * (np.asarray(c3) - np.asarray(c2))))
    pts += [(cx, cy, cz + h / 2), (cx, cy, cz - h / 2)]
    return np.array(pts)


def build_plan(cfg: PlanConfig) -> Plan:
    """The three phases' positionings, each replication in its own random order.

    1. Registration: points at `registration_distances_m` along +x, +y and +z from a common
       origin (the three-line method of Sect. 2.3), `registration_reps` replications.
    2. DOE: every target of `doe_points` at every speed, `doe_reps` replications.
    3. Validation: random points inside the DOE's bounding box at least 60 mm from any DOE point,
       `validation_reps_per_speed` replications per speed.

    Parameters
    ----------
    cfg : PlanConfig
        The plan (its seed fixes the orders and the validation points).

    Returns
    -------
    Plan
    """
    rng = np.random.default_rng(cfg.seed)
    origin = np.array(cfg.registration_origin_m)
    reg_pts = [(ax, d, origin + d * np.eye(3)[k]) for k, ax in enumerate("xyz") for d in cfg.registration_distances_m]
    registration = []
    for rep in range(cfg.registration_reps):
        for i in rng.permutation(len(reg_pts)):
            ax, d, p = reg_pts[i]
            registration.append(PlanRow("registration", int(i), rep, p, cfg.registration_speed, ax, float(d)))

    pts = doe_points(cfg)
    combos = [(i, v) for i in range(len(pts)) for v in cfg.doe_speeds]
    doe = []
    for rep in range(cfg.doe_reps):
        for j in rng.permutation(len(combos)):
            i, v = combos[j]
            doe.append(PlanRow("doe", int(i), rep, pts[i], v))

    lo, hi = pts.min(0), pts.max(0)
    val_list: list[np.ndarray] = []
    while len(val_list) < cfg.validation_points:
        p = rng.uniform(lo, hi)
        if np.min(np.linalg.norm(pts - p, axis=1)) >= 0.06:
            val_list.append(p)
    val_pts = np.array(val_list)
    validation = []
    rep = 0
    for v in cfg.validation_speeds:
        for _ in range(cfg.validation_reps_per_speed):
            for i in rng.permutation(len(val_pts)):
                validation.append(PlanRow("validation", int(i), rep, val_pts[i], v))
            rep += 1
    return Plan(registration, doe, validation, pts, val_pts)
