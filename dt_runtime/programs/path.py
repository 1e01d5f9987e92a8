"""A program that is a path: linear and circular segments (or a dense list of timed poses) with
speed and acceleration limits, and its interpolation into timed set-points at a controller's rate.

The path file (YAML, docs/cli.md "Path programs"; mm, s, the robot base frame, as every file of the
project) is validated at the boundary into frozen models: a bad key, value or geometry is a
ConfigError naming the file, the key (`segments.3.arc.via`), the value and what is allowed.

Interpolation (`interpolate`): the time-optimal trapezoidal speed profile along the path's arc
length under the limits. Each segment has its speed limit (its own `speed` or the path's), an arc
also sqrt(a r) so that its centripetal acceleration v^2 / r stays within the acceleration limit a;
the tangential acceleration is within a everywhere. A junction where the path's tangent is
continuous (within CORNER_RAD) is passed at the highest speed both neighbours and the acceleration
over the path around it allow (forward and backward passes over the junctions); a corner is a stop
(turning there at speed would need an infinite acceleration). Each segment then accelerates at a,
cruises and decelerates at a. With a `jerk` limit j, an S-curve: the trapezoid averaged over a
moving window of a / j s (docs/streaming.md, "Path profiles"). Timed poses are followed as given
(piecewise linear in time), their speeds and accelerations checked against the limits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import ConfigError, DataError
from dt_kernel.units import M_PER_MM
from dt_runtime.measurements.cells import ColumnSpec, parse_rows, read_header

FORMAT = 1
CORNER_RAD = 1e-3  # tangents closer than this are continuous (a junction passed at speed)
MAX_SETPOINTS = 5_000_000  # an interpolated path is held whole: bound what that may cost
MIN_LENGTH_MM = 1e-6  # a shorter segment is a typo (a repeated point), not a move
Finite = Annotated[float, Field(allow_inf_nan=False)]
Point = tuple[Finite, Finite, Finite]


class Line(Frozen):
    """A straight move to `to` (mm); speed (mm/s) caps the path's for this segment."""

    to: Point
    speed: Annotated[float, Field(gt=0, le=5000)] | None = None


class Arc(Frozen):
    """A circular move through `via` to `to` (mm): the circle through the start, via and to."""

    via: Point
    to: Point
    speed: Annotated[float, Field(gt=0, le=5000)] | None = None


class Segment(Frozen):
    """One list entry of `segments`: exactly one of `line` or `arc`."""

    line: Line | None = None
    arc: Arc | None = None


class PathFile(Frozen):
    """A path program (YAML). `start` and either `segments` or `poses` (a CSV of t, x, y, z)."""

    path: Literal[1] = 1  # the format's version
    start: Point | None = None  # mm, robot base frame (segments start here)
    speed: Annotated[float, Field(gt=0, le=5000)]  # mm/s, the path's speed limit
    acceleration: Annotated[float, Field(gt=0, le=100_000)]  # mm/s^2, tangential and centripetal limit
    jerk: Annotated[float, Field(gt=0, le=10_000_000)] | None = None  # mm/s^3: an S-curve (none: a trapezoid)
    segments: list[Segment] | None = None
    poses: str | None = None  # a CSV of timed poses t (s), x, y, z (mm), relative to this file
    # The cell's conditions along the path, for maps that read them (Twin.needs): constant here.
    joints: list[Finite] | None = None  # rad: where the arm stands at the start (the IK starts there)
    temperature: Annotated[float, Field(ge=-20, le=80)] | None = None  # deg C
    payload: Annotated[float, Field(ge=0, le=1000)] | None = None  # kg
    t0: Finite | None = None  # s: the campaign's time at the path's start (drift reads t0 + t)


@dataclass(frozen=True)
class Piece:
    """One segment in SI: a line (centre None) or an arc (centre, radius, in-plane basis u, w)."""

    p0: np.ndarray
    p1: np.ndarray
    length: float  # m
    vmax: float  # m/s: the segment's speed limit (an arc's includes sqrt(a r))
    speed: float  # m/s: the programmed speed (the map's speed input)
    centre: np.ndarray | None = None
    radius: float = 0.0
    u: np.ndarray = field(default_factory=lambda: np.zeros(3))  # unit vector centre -> p0 (arcs)
    w: np.ndarray = field(default_factory=lambda: np.zeros(3))  # in the plane, 90 degrees ahead of u
    sweep: float = 0.0  # rad

    def at(self, s: np.ndarray) -> np.ndarray:
        """Points along the segment.

        Parameters
        ----------
        s : ndarray
            (n,) m, arc lengths from p0.

        Returns
        -------
        ndarray
            (n, 3) m.
        """
        if self.centre is None:
            return self.p0 + np.outer(s / self.length, self.p1 - self.p0)
        ang = s / self.radius
        return self.centre + self.radius * (np.outer(np.cos(ang), self.u) + np.outer(np.sin(ang), self.w))

    def tangent(self, end: bool) -> np.ndarray:
        """The unit tangent (direction of travel) at the segment's start or end.

        Parameters
        ----------
        end : bool
            True: at p1; False: at p0.

        Returns
        -------
        ndarray
            (3,).
        """
        if self.centre is None:
            return (self.p1 - self.p0) / self.length
        ang = self.sweep if end else 0.0
        return np.asarray(-math.sin(ang) * self.u + math.cos(ang) * self.w)


@dataclass(frozen=True)
class PathProgram:
    """A validated path in SI: pieces (segments) or timed poses, and its conditions."""

    source: str
    acceleration: float  # m/s^2
    speed: float  # m/s
    pieces: tuple[Piece, ...] = ()
    jerk: float | None = None  # m/s^3: the S-curve's jerk limit (None: the trapezoid)
    pose_t: np.ndarray | None = None  # (n,) s
    pose_p: np.ndarray | None = None  # (n, 3) m
    pose_line: tuple[int, ...] = ()
    pose_source: str = ""  # the poses CSV, for messages
    joints: np.ndarray | None = None
    temperature: float | None = None
    payload: float | None = None
    t0: float | None = None


@dataclass(frozen=True)
class Setpoints:
    """A path interpolated at `rate_hz`: set-point k at t[k] (s), position p[k] (m, robot base frame),
    speed[k] (m/s, the profile's), segment[k] (0-based: the segment or pose interval it lies on),
    programmed[k] (m/s: the segment's programmed speed, what the error map reads as speed)."""

    t: np.ndarray
    p: np.ndarray
    speed: np.ndarray
    segment: np.ndarray
    programmed: np.ndarray
    rate_hz: float

    @property
    def n(self) -> int:
        """Number of set-points."""
        return len(self.t)


def _arc(p0: np.ndarray, via: np.ndarray, p1: np.ndarray, where: str, file: str, value) -> tuple:
    """Centre, radius, basis (u, w) and sweep of the circle from p0 through via to p1."""
    a, b = via - p0, p1 - p0
    n = np.cross(a, b)
    nn = float(n @ n)
    if nn <= 1e-12 * float(a @ a) * float(b @ b):  # sin^2 of the angle at the start: collinear
        raise ConfigError(file, where, value, "three points not on one line (start, via, to): a circle through them")
    # circumcentre of the triangle p0, via, p1 (Ericson, Real-Time Collision Detection, 3.3.5)
    c = p0 + (np.cross(n, a) * float(b @ b) + np.cross(b, n) * float(a @ a)) / (2.0 * nn)
    r = float(np.linalg.norm(p0 - c))
    u = (p0 - c) / r
    nz = n / math.sqrt(nn)  # the motion turns positively about nz (p0 -> via -> p1)
    w = np.cross(nz, u)

    def angle(p):
        d = p - c
        return math.atan2(float(d @ w), float(d @ u)) % (2 * math.pi)

    return c, r, u, w, angle(p1)


def read_path(path: str | Path) -> PathProgram:
    """Read and check a path file (YAML; mm, mm/s, mm/s^2, s, rad: docs/cli.md "Path programs").

    Parameters
    ----------
    path : str or Path
        The path file.

    Returns
    -------
    PathProgram
        In SI (m, m/s, m/s^2).

    Raises
    ------
    ConfigError
        Naming file, key, value and what is allowed.
    DataError
        The file is missing, or a poses CSV's cell is bad (naming file, line, column and value).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such path file")
    m = load_yaml(path, PathFile)
    f = str(path)
    a, v = m.acceleration * M_PER_MM, m.speed * M_PER_MM
    common = dict(source=f, acceleration=a, speed=v, joints=None if m.joints is None else np.array(m.joints),
                  temperature=m.temperature, payload=m.payload, t0=m.t0)
    if (m.segments is None) == (m.poses is None):
        raise ConfigError(f, "segments/poses", None, "exactly one of 'segments' (lines and arcs) or 'poses' "
                          "(a CSV of timed poses t, x, y, z)")
    if m.poses is not None:
        if m.start is not None:
            raise ConfigError(f, "start", list(m.start), "no start with poses (the first pose is the start)")
        t, p, lines = _read_poses((path.parent / m.poses), f)
        if m.jerk is not None:
            raise ConfigError(f, "jerk", m.jerk, "no jerk with poses (they are followed as given)")
        return PathProgram(**common, pose_t=t, pose_p=p, pose_line=lines,  # type: ignore[arg-type]
                           pose_source=str(path.parent / m.poses))
    if m.start is None:
        raise ConfigError(f, "start", "<missing>", "the path's first point [x, y, z] in mm (robot base frame)")
    if not m.segments:
        raise ConfigError(f, "segments", [], "at least one segment ({line: {to: [x, y, z]}} or {arc: {via, to}})")
    p0 = np.array(m.start) * M_PER_MM
    pieces = []
    for i, seg in enumerate(m.segments):
        if (seg.line is None) == (seg.arc is None):
            raise ConfigError(f, f"segments.{i}", seg.model_dump(exclude_none=True), "exactly one of 'line' or 'arc'")
        g = seg.line or seg.arc
        assert g is not None
        p1 = np.array(g.to) * M_PER_MM
        speed = (g.speed or m.speed) * M_PER_MM
        if seg.line is not None:
            L = float(np.linalg.norm(p1 - p0))
            if L < MIN_LENGTH_MM * M_PER_MM:
                raise ConfigError(f, f"segments.{i}.line.to", list(g.to), "a point other than the segment's start")
            pieces.append(Piece(p0, p1, L, min(speed, v), speed))
        else:
            assert seg.arc is not None
            via = np.array(seg.arc.via) * M_PER_MM
            shortest = min(np.linalg.norm(via - p0), np.linalg.norm(p1 - via), np.linalg.norm(p1 - p0))
            if shortest < MIN_LENGTH_MM * M_PER_MM:
                raise ConfigError(f, f"segments.{i}.arc", {"via": list(seg.arc.via), "to": list(g.to)},
                                  "start, via and to three distinct points (a full circle is two arcs)")
            c, r, u, w, sweep = _arc(p0, via, p1, f"segments.{i}.arc.via", f, list(seg.arc.via))
            pieces.append(Piece(p0, p1, r * sweep, min(speed, v, math.sqrt(a * r)), speed, c, r, u, w, sweep))
        p0 = p1
    return PathProgram(**common, pieces=tuple(pieces),  # type: ignore[arg-type]
                       jerk=None if m.jerk is None else m.jerk * M_PER_MM)


def _read_poses(csv_path: Path, yaml_file: str) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    if not csv_path.is_file():
        raise ConfigError(yaml_file, "poses", str(csv_path), "a CSV file of timed poses t (s), x, y, z (mm) "
                          "(relative to the path file)")
    header = read_header(csv_path, ",")
    need = [c for c in ("t", "x", "y", "z") if c not in header]
    if need:
        raise DataError(f"{csv_path}: timed poses need the columns t (s), x, y, z (mm); missing {', '.join(need)}")
    specs = [ColumnSpec("t", "t")] + [ColumnSpec(k, k, scale=M_PER_MM) for k in ("x", "y", "z")]
    vals, lines, _, _ = parse_rows(csv_path, ",", ".", specs)
    t = np.asarray(vals["t"], float)
    if len(t) < 2:
        raise DataError(f"{csv_path}: {len(t)} poses; a path needs at least 2")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise DataError(f"{csv_path}: line {lines[k]}: column t: value {t[k]:g}: times must increase "
                        f"(the line before holds {t[k - 1]:g} s)")
    return t, np.column_stack([vals[k] for k in ("x", "y", "z")]), tuple(lines)


def _junction_speeds(pieces: tuple[Piece, ...], a: float) -> np.ndarray:
    """Speed at each junction (n + 1): 0 at the ends and at corners, else the highest both
    neighbours allow that the acceleration can reach and leave (forward and backward passes)."""
    n = len(pieces)
    vj = np.zeros(n + 1)
    for k in range(1, n):
        t0, t1 = pieces[k - 1].tangent(True), pieces[k].tangent(False)
        smooth = float(np.clip(t0 @ t1, -1.0, 1.0)) > math.cos(CORNER_RAD)
        vj[k] = min(pieces[k - 1].vmax, pieces[k].vmax) if smooth else 0.0
    for k in range(n):  # forward: what accelerating along segment k can reach
        vj[k + 1] = min(vj[k + 1], math.sqrt(vj[k] ** 2 + 2 * a * pieces[k].length))
    for k in range(n - 1, -1, -1):  # backward: what decelerating along it can leave
        vj[k] = min(vj[k], math.sqrt(vj[k + 1] ** 2 + 2 * a * pieces[k].length))
    return vj


@dataclass(frozen=True)
class _Profile:
    """A segment's trapezoid: accelerate v0 -> vc, cruise, decelerate vc -> v1 (each at a)."""

    v0: float
    vc: float
    v1: float
    a: float
    L: float

    @property
    def t_acc(self) -> float:
        return (self.vc - self.v0) / self.a

    @property
    def t_dec(self) -> float:
        return (self.vc - self.v1) / self.a

    @property
    def t_cruise(self) -> float:
        d = self.L - (self.vc ** 2 - self.v0 ** 2) / (2 * self.a) - (self.vc ** 2 - self.v1 ** 2) / (2 * self.a)
        return max(d, 0.0) / self.vc if self.vc > 0 else 0.0

    @property
    def duration(self) -> float:
        return self.t_acc + self.t_cruise + self.t_dec

    def at(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length and speed at times tau (from the segment's start)."""
        ta, tc, a = self.t_acc, self.t_cruise, self.a
        tau = np.clip(tau, 0.0, self.duration)
        s_a = self.v0 * ta + 0.5 * a * ta ** 2
        s_c = s_a + self.vc * tc
        td = tau - ta - tc
        s = np.where(tau < ta, self.v0 * tau + 0.5 * a * tau ** 2,
                     np.where(td < 0, s_a + self.vc * (tau - ta), s_c + self.vc * td - 0.5 * a * td ** 2))
        v = np.where(tau < ta, self.v0 + a * tau, np.where(td < 0, self.vc, self.vc - a * td))
        return np.minimum(s, self.L), v


def _profile(v0: float, v1: float, vmax: float, a: float, L: float) -> _Profile:
    # the highest cruise the length allows: accelerate to vc and decelerate to v1 within L
    vc = min(vmax, math.sqrt((2 * a * L + v0 ** 2 + v1 ** 2) / 2))
    return _Profile(v0, max(vc, v0, v1), v1, a, L)


def interpolate(path: PathProgram, rate_hz: float) -> Setpoints:
    """The path's timed set-points at `rate_hz`, from t = 0 until its end (the last one, at or
    after the end, holds the end).

    Parameters
    ----------
    path : PathProgram
        The path (`read_path`).
    rate_hz : float
        The controller's set-point rate (Hz), 1 to 10000.

    Returns
    -------
    Setpoints

    Raises
    ------
    DataError
        A rate outside 1-10000 Hz, more than MAX_SETPOINTS set-points, or timed poses faster or
        with a higher acceleration than the path's limits (naming the pose).
    """
    if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 10_000.0):
        raise DataError(f"interpolation rate {rate_hz} Hz: allowed 1 to 10000 Hz (a UR: 125 or 500)")
    if path.pose_t is not None:
        return _interpolate_poses(path, rate_hz)
    a = path.acceleration
    vj = _junction_speeds(path.pieces, a)
    profiles = [_profile(vj[k], vj[k + 1], pc.vmax, a, pc.length) for k, pc in enumerate(path.pieces)]
    starts = np.concatenate([[0.0], np.cumsum([pr.duration for pr in profiles])])
    offsets = np.concatenate([[0.0], np.cumsum([pc.length for pc in path.pieces])])

    def trapezoid(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The path's arc length and speed at times tau (held before 0 and after the end)."""
        k = np.clip(np.searchsorted(starts, tau, side="right") - 1, 0, len(profiles) - 1)
        s, v = np.empty(tau.size), np.empty(tau.size)
        for i, pr in enumerate(profiles):
            sel = k == i
            if sel.any():
                s[sel], v[sel] = pr.at(tau[sel] - starts[i])
        s += offsets[k]
        return np.where(tau <= 0, 0.0, s), np.where((tau <= 0) | (tau >= starts[-1]), 0.0, v)

    if path.jerk is None:
        t = _grid(starts[-1], rate_hz, path.source)
        S, v = trapezoid(t)
    else:
        t, S, v = _s_curve(trapezoid, starts[np.flatnonzero(vj == 0.0)], a / path.jerk, rate_hz, path.source)
    seg = np.clip(np.searchsorted(offsets, S, side="right") - 1, 0, len(path.pieces) - 1)
    p = np.empty((len(t), 3))
    for k, pc in enumerate(path.pieces):
        sel = seg == k
        if sel.any():
            p[sel] = pc.at(np.clip(S[sel] - offsets[k], 0.0, pc.length))
    programmed = np.array([pc.speed for pc in path.pieces])[seg]
    return Setpoints(t, p, v, seg, programmed, rate_hz)


def _s_curve(trapezoid, stops: np.ndarray, t_j: float, rate_hz: float, source: str):
    """The S-curve: set-point times t and the arc length and speed there, each stretch between two
    stops (the ends and the corners, at trapezoid times `stops`) averaged over the window
    [tau - t_j, tau] of its own trapezoid (held at the stretch's ends, so the arm still stops at a
    corner) and t_j longer. The speed (the average's derivative) is exact; the arc length
    integrates the piecewise quadratic trapezoid on a fine grid (trapezoidal rule: h^2 a / 12, below
    a nanometre)."""
    n_str = len(stops) - 1
    begin = stops[:-1] + t_j * np.arange(n_str)  # each stretch's start on the S-curve's clock
    t = _grid(stops[-1] + n_str * t_j, rate_hz, source)
    S, v = np.empty(t.size), np.empty(t.size)
    which = np.clip(np.searchsorted(begin, t, side="right") - 1, 0, n_str - 1)
    for i in range(n_str):
        sel = which == i
        S[sel], v[sel] = _averaged(trapezoid, stops[i], stops[i + 1], t_j, t[sel] - begin[i] + stops[i])
    return t, S, v


def _averaged(trapezoid, a0: float, a1: float, t_j: float, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and speed at times tau of the trapezoid held outside [a0, a1] and averaged over
    [tau - t_j, tau]."""
    def held(x: np.ndarray) -> np.ndarray:
        return trapezoid(np.clip(x, a0, a1))[0]

    h = min(1e-4, t_j / 50.0)
    fine = np.arange(a0 - t_j, a1 + 2 * h, h)
    s_fine = held(fine)
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (s_fine[1:] + s_fine[:-1]) * h)])

    def integrated(x: np.ndarray) -> np.ndarray:  # from a0 - t_j to x, the arc length held beyond
        return np.interp(x, fine, integral) + s_fine[-1] * np.maximum(x - fine[-1], 0.0)

    return (integrated(tau) - integrated(tau - t_j)) / t_j, (held(tau) - held(tau - t_j)) / t_j


def _grid(duration: float, rate_hz: float, source: str) -> np.ndarray:
    """Set-point times k / rate from 0 until the end is reached: the last one at or after the end
    holds the end (a controller's rate is constant; the arm stands there)."""
    n = int(math.ceil(duration * rate_hz - 1e-9)) + 1
    if n > MAX_SETPOINTS:
        raise DataError(f"{source}: {n} set-points at {rate_hz:g} Hz, more than {MAX_SETPOINTS}")
    return np.arange(n) / rate_hz


def _interpolate_poses(path: PathProgram, rate_hz: float) -> Setpoints:
    """Timed poses followed piecewise linearly; DataError naming the pose whose speed or
    acceleration exceeds the path's limits."""
    assert path.pose_t is not None and path.pose_p is not None
    tp, pp = path.pose_t - path.pose_t[0], path.pose_p
    dt = np.diff(tp)
    vel = np.diff(pp, axis=0) / dt[:, None]
    sp = np.linalg.norm(vel, axis=1)
    lim = 1.0 + 1e-9
    fast = np.flatnonzero(sp > path.speed * lim)
    if fast.size:
        k = int(fast[0]) + 1
        raise DataError(f"{path.pose_source}: pose at line {path.pose_line[k]} (t {path.pose_t[k]:g} s): speed "
                        f"{sp[k - 1] * 1e3:.1f} mm/s since the pose before exceeds the path's "
                        f"{path.speed * 1e3:g} mm/s")
    if len(dt) > 1:
        acc = np.linalg.norm(np.diff(vel, axis=0), axis=1) / (0.5 * (dt[1:] + dt[:-1]))
        hard = np.flatnonzero(acc > path.acceleration * lim)
        if hard.size:
            k = int(hard[0]) + 1
            raise DataError(f"{path.pose_source}: pose at line {path.pose_line[k]} (t {path.pose_t[k]:g} s): "
                            f"acceleration {acc[k - 1] * 1e3:.0f} mm/s^2 exceeds the path's "
                            f"{path.acceleration * 1e3:g} mm/s^2")
    t = _grid(tp[-1], rate_hz, path.source)
    seg = np.clip(np.searchsorted(tp, t, side="right") - 1, 0, len(dt) - 1)
    frac = np.minimum((t - tp[seg]) / dt[seg], 1.0)
    p = pp[seg] + frac[:, None] * (pp[seg + 1] - pp[seg])
    return Setpoints(t, p, sp[seg], seg, sp[seg], rate_hz)
