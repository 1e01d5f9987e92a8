"""The twin's numpy kinematics agree with the simulator's PyBullet model and the UR10 data."""
import numpy as np

from dt_runtime.frames.kinematics import load_robot
from dt_runtime.common.paths import CONFIGS


def test_urdf_chain_matches_pybullet():
    from sim.kinematics import Arm  # the test may use sim; dt_runtime code may not

    chain = load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")
    arm = Arm()
    q = np.random.default_rng(0).uniform(-1, 1, (5, 6))
    ref = np.array([arm.fk(qq)[0] for qq in q])
    assert np.max(np.abs(chain.fk(q) - ref)) < 2e-7  # PyBullet reports float32 poses
    Jref = np.array([arm.jacobian(qq)[:3] for qq in q])
    assert np.allclose(chain.jacobian(q), Jref, atol=1e-9)
    arm.close()


def test_jacobian_matches_finite_differences():
    chain = load_robot(CONFIGS / "robots" / "ur10.yaml")
    q = np.random.default_rng(1).uniform(-2, 2, (3, 6))
    J = chain.jacobian(q)
    h = 1e-7
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        num = (chain.fk(q + dq) - chain.fk(q - dq)) / (2 * h)
        assert np.allclose(J[:, :, j], num, atol=1e-7)
