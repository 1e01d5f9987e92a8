"""The one correction law (`twin.corrector.Corrector`) gives the paper's numbers, written plainly in
tests/support/reference_correction.py: the command, U (Eq. 11 at the position, with its labelled
budget) and the volume flag; its geometric design row on floats is the effect's; a warm start
reaches the same fixed point with fewer map evaluations."""
import numpy as np
import pytest

from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.twin import Twin
from tests.support.reference_correction import ReferenceCorrector


# U through the compiled fixed point (twin.law_kernel): the command is the plain law's to 1e-12 m, U
# to U_ROUNDING. The plain law's own U moves by ~2e-12 m when its input moves by one ulp (the GP's
# variance sf2 - k' K^-1 k cancels: tests/unit/test_compiled_law.py shows it), so a path that sums
# in another order cannot be held closer than that; the numpy path (compiled=False) is held at 1e-12.
U_ROUNDING = 1e-11  # m (1e-8 mm)


@pytest.mark.parametrize("compiled", [False, True])
def test_equals_the_plain_law_inside_and_outside_the_volume(twin_dir, compiled):
    twin = Twin.load(twin_dir)
    fast, ref_law = Corrector(twin, compiled=compiled), ReferenceCorrector(twin)
    u_tol = U_ROUNDING if fast.compiled else 1e-12
    rng = np.random.default_rng(3)
    targets = np.array([0.9, 0.0, 0.55]) + rng.uniform(-0.25, 0.25, (60, 3))  # some outside the DOE hull
    inside = []
    for t in targets:
        v = float(rng.uniform(0.1, 1.0))
        ref, got = ref_law.correct(t, v), fast.correct(t, v)
        assert got.command == pytest.approx(ref.command, abs=1e-12)  # 1e-9 mm
        assert got.U == pytest.approx(ref.U, abs=u_tol)
        assert got.inside == ref.inside and got.distance_m == pytest.approx(ref.distance_m, abs=1e-12)
        assert got.joints is None  # the paper's map reads no joints
        inside.append(ref.inside)
    assert 0 < sum(inside) < len(inside)  # both cases were compared


def test_the_twins_api_is_the_law_with_its_labelled_budget(twin_dir):
    twin = Twin.load(twin_dir)
    ref_law = ReferenceCorrector(Twin.load(twin_dir))
    rng = np.random.default_rng(4)
    for t in np.array([0.9, 0.0, 0.55]) + rng.uniform(-0.25, 0.25, (20, 3)):
        got, ref = twin.correct(t, 0.4), ref_law.correct(t, 0.4)
        assert got.command == pytest.approx(ref.command, abs=1e-12)
        assert got.U == pytest.approx(ref.U, abs=U_ROUNDING)
        assert got.budget is not None and ref.budget is not None
        assert [c.label for c in got.budget.components] == [c.label for c in ref.budget.components]
        for a, b in zip(got.budget.components, ref.budget.components):
            assert a.u == pytest.approx(b.u, abs=U_ROUNDING) and a.dof == pytest.approx(b.dof)
        # the figure and its budget agree: the GUM budget's U times the held-out conformal factor
        assert twin.conformal.factor * got.budget.expanded() == pytest.approx(got.U, abs=1e-12)
        assert twin.corrected_command(t, 0.4) == pytest.approx(got.command, abs=1e-15)
    assert twin.corrector is twin.corrector  # built once


@pytest.mark.parametrize("robot", ["cobot_hc20_like.yaml", "ur10.yaml", "catalogue/panda.yaml", "catalogue/iiwa7.yaml"])
def test_the_geometric_row_on_floats_is_the_effects_regressors(robot):
    """geometric_row (a set-point's design row) equals the geometric effect's batched regressors,
    on 6- and 7-axis arms with z and non-z joint axes."""
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.frames.kinematics import load_robot
    from dt_runtime.frames.newton_ik import NewtonIK
    from dt_runtime.models.effects import Inputs
    from dt_runtime.models.effects.geometric import Geometric
    from dt_runtime.twin.corrector import geometric_row

    chain = load_robot(CONFIGS / "robots" / robot)
    ik = NewtonIK(chain)
    rng = np.random.default_rng(5)
    q = rng.uniform(-1.5, 1.5, (5, chain.dof))
    ref = Geometric().regressors(Inputs(commanded=chain.fk(q), joints=q), chain).A
    for k in range(len(q)):
        assert geometric_row(ik, q[k]) == pytest.approx(ref[k], abs=1e-13)


def test_a_warm_start_from_the_previous_set_point_reaches_the_same_command_with_fewer_map_evaluations(twin_dir):
    twin = Twin.load(twin_dir)
    for compiled in (True, False):
        cold, warm = Corrector(twin, compiled=compiled), Corrector(twin, compiled=compiled)
        line = np.column_stack([np.linspace(0.85, 0.95, 200), np.zeros(200), np.full(200, 0.55)])  # 0.5 mm apart
        prev = None
        for x in line:
            a = cold.correct(x, 0.25)
            b = warm.correct(x, 0.25, warm=prev)
            assert b.command == pytest.approx(a.command, abs=2e-8)  # the same fixed point, to its tolerance
            assert b.U == pytest.approx(a.U, abs=1e-9)
            prev = b.command - x
        assert 0 < warm.evaluations < 0.8 * cold.evaluations, (compiled, warm.evaluations, cold.evaluations)


def test_follow_is_the_law_along_a_timed_path(twin_dir):
    """The streaming loop's callable: each set-point at its own programmed speed, warm-started."""
    twin = Twin.load(twin_dir)
    times = np.linspace(0.0, 0.4, 50)
    speeds = np.where(times < 0.2, 0.1, 0.3)
    line = np.column_stack([np.linspace(0.85, 0.95, 50), np.zeros(50), np.full(50, 0.55)])
    follow, cold = Corrector(twin).follow(times, speeds), Corrector(twin)
    for k in range(50):
        assert follow(line[k], float(times[k])) == pytest.approx(cold.correct(line[k], float(speeds[k])).command,
                                                                 abs=2e-8)
