"""The few URScript commands the UR driver sends to the controller's script port (movel, stopl,
the set-point servo program), and a strict parser of exactly those for the emulator (anything
else is refused, as a script error would be). Poses are p[x, y, z, rx, ry, rz] (m, rotation
vector in rad, base frame); numbers are written with 9 decimals and no exponent. The accepted
programs and the servo program's loop: docs/drivers.md ("Streaming set-points" and "The wire
formats")."""
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


# What the servo program writes into its status output register.
STREAM_RUNNING, STREAM_WATCHDOG, STREAM_HOST_STOP = 1, 2, 3
STREAM_STATES = {0: "not started", STREAM_RUNNING: "running", STREAM_WATCHDOG: "stopped by the watchdog",
                 STREAM_HOST_STOP: "stopped by the host"}


@dataclass(frozen=True)
class ServoProgram:
    """The parameters of the servo program (see the module docstring); registers are numbers 0-47."""

    double_register: int  # first of six input double registers: x, y, z (m), rx, ry, rz (rad)
    seq_register: int  # input int register: the host's set-point sequence number (< 0: stop)
    status_register: int  # output int register: STREAM_*; the next one echoes the sequence taken
    period_s: float  # servoj's t: the control period (0.008 CB3, 0.002 e-Series)
    lookahead_s: float  # servoj's lookahead_time
    gain: float  # servoj's gain
    watchdog_cycles: int  # control cycles without a new sequence number before the arm is stopped
    stop_a: float  # stopj's deceleration (rad/s^2)

    @property
    def echo_register(self) -> int:
        """The output int register where the program echoes the sequence number it took: ``status_register + 1``."""
        return self.status_register + 1


@dataclass(frozen=True)
class Command:
    """One parsed command: ``kind`` (movel, movej, stopl, stopj, servo), ``a`` (acceleration or
    deceleration), ``v`` (speed), ``pose`` (x, y, z m, rx, ry, rz rad) or ``q`` (rad), and for
    ``servo`` the program's parameters.
    """
    kind: str  # movel, movej, stopl, stopj, servo
    a: float
    v: float = 0.0
    pose: tuple[float, ...] | None = None  # p[...]: x, y, z (m), rx, ry, rz (rad)
    q: tuple[float, ...] | None = None  # [...]: joint positions (rad)
    servo: ServoProgram | None = None  # kind "servo": the servo program's parameters


def _num(x: float) -> str:
    if not math.isfinite(x):
        raise ScriptError(f"URScript has no literal for {x!r}")
    s = f"{x:.9f}"
    return "0.000000000" if s == "-0.000000000" else s


def movel(pose: Sequence[float], a: float, v: float) -> str:
    """One-line program: linear move to a pose.

    Parameters
    ----------
    pose : sequence of float
        6 values: x, y, z (m), rx, ry, rz (rad, rotation vector), base frame.
    a : float
        Acceleration (m/s^2).
    v : float
        Speed (m/s).

    Returns
    -------
    str
        The line, with its newline.

    Raises
    ------
    ScriptError
        When the pose has not 6 values or a number is not finite.
    """
    if len(pose) != 6:
        raise ScriptError(f"movel needs a pose of 6 values, got {len(pose)}")
    return f"movel(p[{','.join(_num(float(x)) for x in pose)}], a={_num(a)}, v={_num(v)})\n"


def stopl(a: float) -> str:
    """One-line program: decelerate the TCP to a stop.

    Parameters
    ----------
    a : float
        Deceleration (m/s^2).

    Returns
    -------
    str

    Raises
    ------
    ScriptError
        When ``a`` is not finite.
    """
    return f"stopl({_num(a)})\n"


def servo_program(sp: ServoProgram) -> str:
    """The servo program's text for these parameters (``def dt_servo(): ... end``).

    Parameters
    ----------
    sp : ServoProgram

    Returns
    -------
    str

    Raises
    ------
    ScriptError
        When a register or the watchdog is out of range, or a number is not finite.
    """
    d, s, e, st = sp.double_register, sp.seq_register, sp.echo_register, sp.status_register
    if not (0 <= d <= 42 and 0 <= s <= 47 and 0 <= st <= 46 and sp.watchdog_cycles >= 1):
        raise ScriptError(f"servo program: registers or watchdog out of range: {sp}")
    regs = ", ".join(f"read_input_float_register({d + i})" for i in range(6))
    return "\n".join([
        "def dt_servo():",
        "  # cobot-dt set-point stream (drivers.ur.urscript.servo_program)",
        f"  write_output_integer_register({st}, {STREAM_RUNNING})",
        f"  dt_seen = read_input_integer_register({s})",
        "  dt_quiet = 0",
        "  while True:",
        f"    dt_seq = read_input_integer_register({s})",
        "    if dt_seq < 0:",
        f"      write_output_integer_register({st}, {STREAM_HOST_STOP})",
        f"      stopj({_num(sp.stop_a)})",
        "      halt",
        "    end",
        "    if dt_seq == dt_seen:",
        "      dt_quiet = dt_quiet + 1",
        f"      if dt_quiet > {sp.watchdog_cycles}:",
        f"        write_output_integer_register({st}, {STREAM_WATCHDOG})",
        f"        textmsg(\"cobot-dt stream watchdog: no new set-point for {sp.watchdog_cycles} control cycles\")",
        f"        stopj({_num(sp.stop_a)})",
        "        halt",
        "      end",
        "    else:",
        "      dt_seen = dt_seq",
        "      dt_quiet = 0",
        "    end",
        f"    write_output_integer_register({e}, dt_seen)",
        f"    dt_x = p[{regs}]",
        f"    servoj(get_inverse_kin(dt_x, qnear=get_actual_joint_positions()), 0, 0, {_num(sp.period_s)}, "
        f"{_num(sp.lookahead_s)}, {_num(sp.gain)})",
        "  end",
        "end",
        ""])


def program_end(lines: list[str]) -> int | None:
    """Index of the ``end`` closing the block opened by lines[0] (``def ...:``).

    ``if``/``while``/``def`` open a block, ``else:``/``elif`` continue one.

    Parameters
    ----------
    lines : list of str
        Program lines received so far.

    Returns
    -------
    int or None
        None when the block is not complete yet.
    """
    depth = 0
    for i, raw in enumerate(lines):
        ln = raw.split("#", 1)[0].strip()
        if ln == "end":
            depth -= 1
            if depth == 0:
                return i
        elif ln.endswith(":") and re.match(r"^(def|if|while)\b", ln):
            depth += 1
    return None


_SERVO_PARAMS = {
    "double_register": (r"dt_x = p\[read_input_float_register\((\d+)\)", int),
    "seq_register": (r"dt_seen = read_input_integer_register\((\d+)\)", int),
    "status_register": (r"^write_output_integer_register\((\d+), 1\)", int),
    "watchdog_cycles": (r"if dt_quiet > (\d+):", int),
    "stop_a": (rf"stopj\(({_NUM})\)", float),
    "period_s": (rf"servoj\(.*\), 0, 0, ({_NUM}), ", float),
    "lookahead_s": (rf"servoj\(.*\), 0, 0, {_NUM}, ({_NUM}), ", float),
    "gain": (rf"servoj\(.*\), 0, 0, {_NUM}, {_NUM}, ({_NUM})\)$", float),
}


def _norm(text: str) -> list[str]:
    lines = [ln.split("#", 1)[0].strip() for ln in text.replace("\r", "").split("\n")]
    return [ln for ln in lines if ln]


def parse_servo(text: str) -> ServoProgram:
    """The parameters of a servo program, if ``text`` is exactly what ``servo_program`` writes
    for them (comments and indentation aside).

    Parameters
    ----------
    text : str

    Returns
    -------
    ServoProgram

    Raises
    ------
    ScriptError
        When a parameter is missing or the text is not that program.
    """
    lines = _norm(text)
    found = {}
    for key, (pattern, typ) in _SERVO_PARAMS.items():
        m = next((m for ln in lines if (m := re.search(pattern, ln))), None)
        if m is None:
            raise ScriptError(f"servo program: no {key} found")
        found[key] = typ(m.group(1))
    sp = ServoProgram(**found)
    if _norm(servo_program(sp)) != lines:
        raise ScriptError("servo program: not the dt_servo program this controller runs "
                          "(drivers.ur.urscript.servo_program)")
    return sp


def parse(text: str) -> list[Command]:
    """The commands of a one-line program or a ``def ...: end`` block.

    Parameters
    ----------
    text : str

    Returns
    -------
    list of Command

    Raises
    ------
    ScriptError
        For an empty program, a block without its ``end``, or any command not accepted here.
    """
    lines = _norm(text)
    if not lines:
        raise ScriptError("empty program")
    if lines[0] == "def dt_servo():":
        sp = parse_servo(text)
        return [Command("servo", sp.stop_a, servo=sp)]
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
