"""Path programs (programs.path): the file format (good and bad files, errors naming file, key and
value), and the interpolation (rate, limits honoured, continuity, circular arcs exact)."""
import math

import numpy as np
import pytest

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.programs.path import interpolate, read_path

SEAM = """path: 1
start: [900, 0, 550]
speed: 250
acceleration: 2000
segments:
  - line: {to: [950, 0, 550]}
  - arc: {via: [985.35533906, 14.64466094, 550], to: [1000, 50, 550]}
  - line: {to: [1000, 120, 550], speed: 100}
  - line: {to: [1000, 120, 600]}
"""


def _write(tmp_path, text, name="p.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_a_seam_is_interpolated_within_its_limits(tmp_path):
    path = read_path(_write(tmp_path, SEAM))
    assert [round(pc.length * 1e3, 6) for pc in path.pieces] == [50.0, round(25 * math.pi, 6), 70.0, 50.0]
    sp = interpolate(path, 500)
    assert np.allclose(np.diff(sp.t), 0.002)  # the rate, constant to the end
    assert sp.p[0] * 1e3 == pytest.approx([900, 0, 550]) and sp.p[-1] * 1e3 == pytest.approx([1000, 120, 600])
    # the finite-difference speed and tangential acceleration honour the limits
    v = np.linalg.norm(np.diff(sp.p, axis=0), axis=1) / np.diff(sp.t)
    assert v.max() <= 0.250 + 1e-9 and sp.speed.max() == pytest.approx(0.250)
    assert np.abs(np.diff(sp.speed)).max() * 500 <= 2.0 + 1e-9
    assert sp.speed[sp.segment == 2].max() == pytest.approx(0.100)  # the segment's own limit
    # continuity: no jump between consecutive set-points beyond what the speed allows
    assert np.linalg.norm(np.diff(sp.p, axis=0), axis=1).max() <= 0.250 / 500 + 1e-12
    # line -> arc is tangent: passed at speed; the arc -> line junction too; line -> up is a corner: a stop
    t_junction = [sp.t[np.flatnonzero(sp.segment == k)[0]] for k in (1, 2, 3)]
    speed_at = [float(np.interp(t, sp.t, sp.speed)) for t in t_junction]
    assert speed_at[0] > 0.24 and speed_at[1] == pytest.approx(0.100, abs=0.005) and speed_at[2] < 0.005
    assert sp.speed[0] == 0.0 and sp.speed[-1] == pytest.approx(0.0, abs=1e-12)


def test_an_arc_is_exact_and_its_speed_capped_by_the_centripetal_limit(tmp_path):
    # a half circle of radius 20 mm: sqrt(a r) = sqrt(2 m/s^2 * 0.02 m) = 0.2 m/s < 0.25 m/s
    path = read_path(_write(tmp_path, """start: [900, 0, 550]
speed: 250
acceleration: 2000
segments:
  - arc: {via: [920, 20, 550], to: [940, 0, 550]}
"""))
    pc = path.pieces[0]
    assert pc.centre * 1e3 == pytest.approx([920, 0, 550]) and pc.radius == pytest.approx(0.02)
    assert pc.sweep == pytest.approx(math.pi) and pc.vmax == pytest.approx(math.sqrt(2.0 * 0.02))
    sp = interpolate(path, 125)
    r = np.linalg.norm(sp.p - pc.centre, axis=1)
    assert np.abs(r - 0.02).max() < 1e-12 and np.abs(sp.p[:, 2] - 0.55).max() < 1e-12
    assert sp.p[:, 1].min() > -1e-12  # through the via side (y > 0), not the other half
    assert (sp.speed ** 2 / 0.02).max() <= 2.0 + 1e-9  # centripetal acceleration within the limit
    # the trapezoid's duration: accelerate to 0.2 m/s, cruise, decelerate
    L, vc, a = math.pi * 0.02, math.sqrt(0.04), 2.0
    T = L / vc + vc / a
    assert sp.t[-2] < T <= sp.t[-1] and sp.p[-1] * 1e3 == pytest.approx([940, 0, 550], abs=1e-9)


def test_a_short_line_never_reaches_its_speed(tmp_path):
    sp = interpolate(read_path(_write(tmp_path, "start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\n"
                                                "segments: [{line: {to: [905, 0, 550]}}]\n")), 500)
    # triangle: v_peak = sqrt(a L) = 0.1 m/s, t = 2 sqrt(L / a) = 0.1 s
    assert sp.speed.max() <= 0.1 + 1e-12 and sp.n == 51 and sp.t[-1] == pytest.approx(0.1, rel=1e-12)


def test_timed_poses_are_followed_and_checked(tmp_path):
    (tmp_path / "poses.csv").write_text("t,x,y,z\n10.0,900,0,550\n10.1,901,0,550\n10.2,902,0.5,550\n")
    path = read_path(_write(tmp_path, "speed: 250\nacceleration: 2000\nposes: poses.csv\n"))
    sp = interpolate(path, 500)
    assert sp.n == 101 and sp.t[-1] == pytest.approx(0.2)
    assert sp.p[50] * 1e3 == pytest.approx([901, 0, 550]) and set(sp.segment.tolist()) == {0, 1}
    (tmp_path / "fast.csv").write_text("t,x,y,z\n0,900,0,550\n0.1,900,0,550\n0.11,905,0,550\n")
    with pytest.raises(DataError, match=r"fast.csv: pose at line 4 \(t 0.11 s\): speed 500.0 mm/s"):
        interpolate(read_path(_write(tmp_path, "speed: 250\nacceleration: 2000\nposes: fast.csv\n")), 500)
    (tmp_path / "back.csv").write_text("t,x,y,z\n0,900,0,550\n0.2,900,0,550\n0.1,901,0,550\n")
    with pytest.raises(DataError, match=r"back.csv: line 4: column t: value 0.1: times must increase"):
        read_path(_write(tmp_path, "speed: 250\nacceleration: 2000\nposes: back.csv\n"))


@pytest.mark.parametrize("text, key, allowed", [
    ("start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\nsegments: [{line: {to: [950, 0]}}]\n",
     "segments.0.line.to.2", ""),
    ("start: [900, 0, 550]\nspeed: -5\nacceleration: 2000\nsegments: [{line: {to: [950, 0, 550]}}]\n",
     "speed", "greater than 0"),
    ("start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\nsegments: [{lin: {to: [950, 0, 550]}}]\n",
     "segments.0.lin", "known keys: arc, line"),
    ("start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\nsegments:\n  - line: {to: [950, 0, 550]}\n"
     "  - arc: {via: [960, 0, 550], to: [970, 0, 550]}\n", "segments.1.arc.via", "three points not on one line"),
    ("start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\nsegments: [{line: {to: [900, 0, 550]}}]\n",
     "segments.0.line.to", "a point other than the segment's start"),
    ("start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\n"
     "segments: [{line: {to: [950, 0, 550]}, arc: {via: [1, 2, 3], to: [4, 5, 6]}}]\n", "segments.0", "exactly one"),
    ("speed: 250\nacceleration: 2000\nsegments: [{line: {to: [950, 0, 550]}}]\n", "start", "first point"),
    ("start: [900, 0, 550]\nspeed: 250\nacceleration: 2000\n", "segments/poses", "exactly one of"),
    ("start: [900, 0, .nan]\nspeed: 250\nacceleration: 2000\nsegments: [{line: {to: [950, 0, 550]}}]\n",
     "start.2", "finite"),
    ("path: 2\nstart: [900, 0, 550]\nspeed: 250\nacceleration: 2000\nsegments: [{line: {to: [950, 0, 550]}}]\n",
     "path", "1"),
])
def test_a_bad_path_file_names_file_key_value_and_what_is_allowed(tmp_path, text, key, allowed):
    with pytest.raises(ConfigError) as err:
        read_path(_write(tmp_path, text))
    assert err.value.key == key and str(tmp_path / "p.yaml") in str(err.value) and allowed in str(err.value)


def test_a_bad_rate_is_refused(tmp_path):
    path = read_path(_write(tmp_path, SEAM))
    with pytest.raises(DataError, match="interpolation rate 0.0 Hz"):
        interpolate(path, 0.0)


def test_a_jerk_limit_gives_an_s_curve_on_the_same_geometry(tmp_path):
    """`jerk`: the trapezoid averaged over a / j seconds per stretch between stops: the speed and the
    tangential acceleration stay within the limits, the acceleration ramps (its finite-difference
    jerk within 2 j: a triangular ramp switches from +a to -a), the arm still stops at the corner,
    each stretch is a / j longer, and every set-point lies on the trapezoid's path."""
    trap = interpolate(read_path(_write(tmp_path, SEAM)), 500)
    path = read_path(_write(tmp_path, SEAM.replace("acceleration: 2000", "acceleration: 2000\njerk: 40000"), "j.yaml"))
    assert path.jerk == pytest.approx(40.0)
    sp = interpolate(path, 500)
    t_j = 2.0 / 40.0
    assert sp.t[-1] == pytest.approx(trap.t[-1] + 2 * t_j, abs=2 / 500)  # two stretches: the corner splits the seam
    assert sp.p[0] * 1e3 == pytest.approx([900, 0, 550]) and sp.p[-1] * 1e3 == pytest.approx([1000, 120, 600])
    v = np.linalg.norm(np.diff(sp.p, axis=0), axis=1) * 500
    assert v.max() <= 0.250 + 1e-6 and sp.speed.max() <= 0.250 + 1e-9
    acc = np.diff(sp.speed) * 500
    assert np.abs(acc).max() <= 2.0 + 1e-6
    assert np.abs(np.diff(acc)).max() * 500 <= 2 * 40.0 * 1.01  # jerk-limited: the trapezoid's steps are ramps
    assert np.abs(np.diff(np.diff(trap.speed) * 500)).max() * 500 > 400  # the trapezoid's: steps of a per period
    corner = np.flatnonzero(sp.segment == 3)[0]
    assert sp.speed[corner - 1: corner + 1].min() < 0.005  # still a stop at the corner
    # the same geometry: each set-point on its segment (a line's, or the arc's circle)
    for k, pc in enumerate(path.pieces):
        q = sp.p[sp.segment == k]
        if pc.centre is None:
            u = (pc.p1 - pc.p0) / pc.length
            off = (q - pc.p0) - np.outer((q - pc.p0) @ u, u)
            assert np.linalg.norm(off, axis=1).max() < 1e-9
        else:
            assert np.abs(np.linalg.norm(q - pc.centre, axis=1) - pc.radius).max() < 1e-9


def test_a_jerk_limit_is_refused_with_timed_poses(tmp_path):
    (tmp_path / "poses.csv").write_text("t,x,y,z\n0,900,0,550\n1,900,10,550\n")
    with pytest.raises(ConfigError) as err:
        read_path(_write(tmp_path, "speed: 250\nacceleration: 2000\njerk: 40000\nposes: poses.csv\n"))
    assert err.value.key == "jerk"
