"""The warm-started Newton IK (frames.newton_ik): the same solution as Chain.ik, converged below
1e-9 m in a step or two along a path, and clear errors for unreachable or bad targets."""
import math

import numpy as np
import pytest

from dt_kernel.errors import DataError, UnreachableError
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.frames.newton_ik import NewtonIK, rotvec

ROBOTS = {"cobot_hc20_like.yaml": [0.0, 0.0959, 0.9323, 0.0, -0.4282, 0.0],
          "ur10.yaml": [0.1, -0.8, 1.2, -0.4, 0.9, 0.3]}


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_follows_a_path_as_chain_ik_does_in_two_steps(robot):
    chain = load_robot(CONFIGS / "robots" / robot)
    ik = NewtonIK(chain)
    q0 = np.array(ROBOTS[robot])
    p0, R0 = chain.pose(q0)
    a = np.arange(200) * 0.5e-3 / 0.05  # a 50 mm circle in 0.5 mm steps (250 mm/s at 500 Hz)
    path = p0 + 0.05 * np.column_stack([np.cos(a) - 1, np.sin(a), 0.3 * a])
    q_old = q_new = q0
    steps = []
    for x in path:
        q_old, q_new = chain.ik(x, q_old), ik.solve(x, q_new)
        steps.append(ik.iterations)
        p, R = chain.pose(q_new)
        assert np.linalg.norm(p - x) < 1e-9 and np.linalg.norm(rotvec(R0 @ R.T)) < 1e-9  # orientation held
        assert np.abs(q_new - q_old).max() < 1e-9  # the same solution, the same branch
    assert max(steps) <= 3 and np.mean(steps) <= 2.0


def test_rotvec_is_scipys():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    for v in [rng.normal(size=3) * s for s in (1e-9, 1e-4, 0.5, 2.0, 3.1)] + [np.array([0.0, 0.0, math.pi - 1e-4])]:
        M = Rotation.from_rotvec(v).as_matrix()
        assert rotvec(M) == pytest.approx(Rotation.from_matrix(M).as_rotvec(), abs=1e-9)


def test_unreachable_and_singular_targets_name_the_target():
    chain = load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")
    ik = NewtonIK(chain)
    q0 = np.array(ROBOTS["cobot_hc20_like.yaml"])
    far = np.array([chain.reach_m + 0.3, 0.0, 0.5])
    with pytest.raises(UnreachableError, match=r"target \[\d+\.\d*, 0\.0, 500\.0\] mm: no joint angles of "
                                               r"cobot_hc20_like reach it"):
        ik.solve(far, q0)
    # from a singular seed (q = 0: the geometric Jacobian loses a rank) the damped steps stay bounded
    q_sing = np.zeros(6)
    assert np.linalg.svd(chain.jacobian6(q_sing[None])[0], compute_uv=False)[-1] < 1e-9
    p_sing = chain.fk(q_sing)[0]
    q = ik.solve(p_sing + np.array([-1e-3, 0.0, 1e-3]), q_sing)
    assert np.all(np.isfinite(q)) and np.linalg.norm(chain.fk(q)[0] - p_sing - [-1e-3, 0, 1e-3]) < 1e-9
    with pytest.raises(DataError, match="finite"):
        ik.solve(np.array([np.nan, 0.0, 0.5]), q0)
    with pytest.raises(DataError, match="q_seed 6"):
        ik.solve(np.array([0.9, 0.0, 0.5]), q0[:5])


def test_warm_start_is_cheaper_than_chain_ik():
    """CPU time of both on the same path, same run: the ratio, not a wall-clock threshold."""
    import time

    chain = load_robot(CONFIGS / "robots" / "ur10.yaml")
    ik = NewtonIK(chain)
    q0 = np.array(ROBOTS["ur10.yaml"])
    p0 = chain.pose(q0)[0]
    path = p0 + np.outer(np.arange(100) * 0.5e-3, [0.6, 0.0, 0.8])
    t0 = time.process_time()
    q = q0
    for x in path:
        q = chain.ik(x, q)
    t1 = time.process_time()
    q = q0
    for x in path:
        q = ik.solve(x, q)
    t2 = time.process_time()
    assert (t2 - t1) < 0.5 * (t1 - t0), (t2 - t1, t1 - t0)
