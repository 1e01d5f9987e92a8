"""The servo follower of sim.servo (servoj as UR's manual describes it), the URScript servo program
the UR driver sends and the emulator accepts, and the streaming parameters' ranges."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.base import check_stream_params
from drivers.ur import urscript
from dt_kernel.errors import DriverError
from sim.servo import ServoFollower


def _run(f: ServoFollower, target, n: int, dt: float) -> np.ndarray:
    return np.array([f.step(target(k * dt), dt)[0] for k in range(1, n + 1)])


@pytest.mark.parametrize("lookahead, gain", [(0.03, 1200.0), (0.1, 300.0), (0.2, 100.0), (0.05, 2000.0)])
def test_a_ramp_is_trailed_by_the_lookahead_time_whatever_the_gain(lookahead, gain):
    v = 0.25  # m/s
    f = ServoFollower(np.zeros(1), lookahead, gain)
    x = _run(f, lambda t: np.array([v * t]), 1000, 0.002)  # 2 s at 500 Hz
    lag = v * 2.0 - x[-1, 0]
    assert lag == pytest.approx(v * lookahead, rel=1e-3)


def test_a_short_lookahead_with_a_high_gain_overshoots_a_long_one_does_not():
    under = ServoFollower(np.zeros(1), 0.03, 1200.0)
    assert under.damping_ratio == pytest.approx(0.03 * math.sqrt(1200) / 2)
    x = _run(under, lambda t: np.array([1e-3]), 500, 0.008)
    z = under.damping_ratio
    assert x.max() / 1e-3 - 1 == pytest.approx(math.exp(-math.pi * z / math.sqrt(1 - z * z)), abs=5e-3)  # ~15 %
    assert x[-1, 0] == pytest.approx(1e-3, abs=1e-9)
    damped = ServoFollower(np.zeros(1), 0.2, 100.0)  # zeta 1.0
    assert _run(damped, lambda t: np.array([1e-3]), 500, 0.008).max() <= 1e-3 * (1 + 1e-9)


def test_stop_holds_the_position():
    f = ServoFollower(np.zeros(3), 0.1, 300.0)
    f.step(np.array([0.01, 0.0, 0.0]), 0.05)
    here = f.stop()
    assert np.array_equal(f.v, np.zeros(3)) and np.array_equal(here, f.x)


def test_the_servo_program_round_trips_and_nothing_else_passes_for_it():
    sp = urscript.ServoProgram(30, 25, 36, 0.002, 0.05, 500.0, 40, 3.0)
    text = urscript.servo_program(sp)
    (cmd,) = urscript.parse(text)
    assert cmd.kind == "servo" and cmd.servo == sp and sp.echo_register == 37
    assert "read_input_float_register(35)" in text and "servoj(get_inverse_kin(dt_x" in text
    lines = text.split("\n")
    assert urscript.program_end(lines) == len(lines) - 2  # the def's own end, past the nested ones
    assert urscript.program_end(lines[:-3]) is None  # incomplete
    for edit in [("dt_quiet > 40", "dt_quiet > 4000"), ("halt", "sync()"), ("stopj(3.000000000)", "stopl(3)"),
                 ("if dt_seq < 0:", "if dt_seq < -5:")]:
        bad = text.replace(*edit, 1)
        assert bad != text
        with pytest.raises(urscript.ScriptError):
            urscript.parse(bad)


@pytest.mark.parametrize("rate, lookahead, gain, match", [
    (0.0, 0.1, 300.0, "stream rate"), (600.0, 0.1, 300.0, "stream rate"), (125.0, 0.01, 300.0, "look-ahead"),
    (125.0, 0.3, 300.0, "look-ahead"), (125.0, 0.1, 50.0, "gain"), (125.0, 0.1, float("nan"), "gain"),
])
def test_stream_parameters_outside_servoj_ranges_are_refused(rate, lookahead, gain, match):
    with pytest.raises(DriverError, match=match):
        check_stream_params(rate, lookahead, gain, 500.0)
    assert check_stream_params(125, 0.03, 2000, 500.0) == (125.0, 0.03, 2000.0)
