"""The fast per-set-point correction (twin.setpoint) gives Twin.correct's numbers: the command,
U (Eq. 11 at the position) and the volume flag, on the quick demo's twin (the paper's map)."""
import numpy as np
import pytest

from dt_runtime.twin.setpoint import SetpointCorrector
from dt_runtime.twin.twin import Twin


def test_equals_twin_correct_inside_and_outside_the_volume(twin_dir):
    twin = Twin.load(twin_dir)
    fast = SetpointCorrector(twin)
    rng = np.random.default_rng(3)
    targets = np.array([0.9, 0.0, 0.55]) + rng.uniform(-0.25, 0.25, (60, 3))  # some outside the DOE hull
    inside = []
    for t in targets:
        v = float(rng.uniform(0.1, 1.0))
        ref, got = twin.correct(t, v), fast.correct(t, v)
        assert got.command == pytest.approx(ref.command, abs=1e-12)  # 1e-9 mm
        assert got.U == pytest.approx(ref.U, abs=1e-12)
        assert got.inside == ref.inside and got.distance_m == pytest.approx(ref.distance_m, abs=1e-12)
        assert got.joints is None  # the paper's map reads no joints
        inside.append(ref.inside)
    assert 0 < sum(inside) < len(inside)  # both cases were compared
    c = fast.correct(targets[0], 0.5).correction(targets[0])
    assert c.budget is None and np.array_equal(c.target, targets[0])
