"""The few URScript commands the driver sends to the controller's script port, and a strict parser
of exactly those for the emulator (anything else is refused, as a script error would be).

URScript (Universal Robots, "The URScript Programming Language"): poses are `p[x, y, z, rx, ry,
rz]` in metres and a rotation vector (axis times angle, rad) in the base frame; joint positions
are `[q1, ..., q6]` in rad; `a` is the acceleration (m/s^2 for movel, rad/s^2 for movej) and `v`
the speed (m/s, rad/s). A program sent to the secondary interface (30002) is either one line
("movel(...)\\n") or a `def name(): ... end` block; a new program replaces the running one.

Accepted here::

    movel(p[x,y,z,rx,ry,rz], a=A, v=V)     linear move of the TCP
    movej(p[...] or [q1..q6], a=A, v=V)    joint move (to a pose or joint positions)
    stopl(A) / stopj(A)                    decelerate to a stop

Numbers are written in fixed notation with 9 decimals (1 nm, 1 nrad): no exponent, which every
URScript version parses.
"""
from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

from dt_kernel.errors import DriverError

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_LIST = rf"\[\s*{_NUM}(?:\s*,\s*{_NUM})*\s*\]"
_MOVE = re.compile(rf"^(movel|movej)\(\s*(p?)({_LIST})\s*,\s*a\s*=\s*({_NUM})\s*,\s*v\s*=\s*({_NUM})\s*\)$")
_STOP = re.compile(rf"^(stopl|stopj)\(\s*({_NUM})\s*\)$")
_DEF = re.compile(r"^def\s+[A-Za-z_][A-Za-z0-9_]*\s*\(\s*\)\s*:$")


class ScriptError(DriverError):
    """A script the controller would not run (the emulator reports it as a text message)."""


@dataclass(frozen=True)
class Command:
    kind: str  # movel, movej, stopl, stopj
    a: float
    v: float = 0.0
    pose: tuple[float, ...] | None = None  # p[...]: x, y, z (m), rx, ry, rz (rad)
    q: tuple[float, ...] | None = None  # [...]: joint positions (rad)


def _num(x: float) -> str:
    if not math.isfinite(x):
        raise ScriptError(f"URScript has no literal for {x!r}")
    s = f"{x:.9f}"
    return "0.000000000" if s == "-0.000000000" else s


def movel(pose: Sequence[float], a: float, v: float) -> str:
    """One-line program: linear move to `pose` (6 values) with acceleration `a` and speed `v`."""
    if len(pose) != 6:
        raise ScriptError(f"movel needs a pose of 6 values, got {len(pose)}")
    return f"movel(p[{','.join(_num(float(x)) for x in pose)}], a={_num(a)}, v={_num(v)})\n"


def stopl(a: float) -> str:
    return f"stopl({_num(a)})\n"


def parse(text: str) -> list[Command]:
    """The commands of a one-line program or a `def ...: end` block; ScriptError otherwise."""
    lines = [ln.split("#", 1)[0].strip() for ln in text.replace("\r", "").split("\n")]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise ScriptError("empty program")
    if _DEF.match(lines[0]):
        if lines[-1] != "end" or len(lines) < 2:
            raise ScriptError(f"program '{lines[0]}' has no matching 'end'")
        lines = lines[1:-1]
    out = []
    for ln in lines:
        out.append(_command(ln))
    return out


def _command(line: str) -> Command:
    m = _MOVE.match(line)
    if m:
        kind, is_pose, values, a, v = m.groups()
        nums = tuple(float(x) for x in values.strip("[] ").split(","))
        if len(nums) != 6:
            raise ScriptError(f"{kind}: expected 6 values, got {len(nums)}: {line!r}")
        if kind == "movel" and not is_pose:
            raise ScriptError(f"movel takes a pose p[...]: {line!r}")
        if float(a) <= 0 or float(v) <= 0:
            raise ScriptError(f"{kind}: a and v must be positive: {line!r}")
        return Command(kind, float(a), float(v), pose=nums if is_pose else None, q=None if is_pose else nums)
    m = _STOP.match(line)
    if m:
        if float(m.group(2)) <= 0:
            raise ScriptError(f"{m.group(1)}: deceleration must be positive: {line!r}")
        return Command(m.group(1), float(m.group(2)))
    raise ScriptError(f"not supported by this controller: {line[:80]!r}")
