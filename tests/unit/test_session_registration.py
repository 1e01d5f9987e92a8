"""A new session registered on reference poses (analysis.deployment): the rigid fit's stated
uncertainty covers its real error at points it did not see, and the reference poses are spread."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dt_kernel.errors import DataError
from dt_runtime.analysis import deployment
from dt_runtime.frames.registration import RigidTransform, rigid_uncertainty


def test_the_rigid_fits_uncertainty_covers_its_error_at_unseen_points():
    rng = np.random.default_rng(11)
    truth = RigidTransform(Rotation.from_rotvec([0.02, -0.01, 0.3]).as_matrix(), np.array([1.2, -0.4, 0.1]))
    ref = rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 0.6], (10, 3))
    probe = rng.uniform([-0.8, -0.8, 0.0], [0.8, 0.8, 0.9], (50, 3))
    z = []
    for _ in range(400):
        fit = rigid_uncertainty(ref, truth.apply(ref) + rng.normal(0, 2e-5, ref.shape))
        z.append((fit.T.apply(probe) - truth.apply(probe)) / fit.at(probe))
    z = np.concatenate(z)
    assert fit.dof == 24
    assert np.std(z) == pytest.approx(1.0, abs=0.12)  # the stated u is the real spread, also outside the poses
    t = 2.064  # t(0.975, 24)
    assert 0.93 <= float(np.mean(np.abs(z) <= t)) <= 0.97


def test_reference_poses_are_spread_and_take_every_replicate():
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 1, (30, 3))
    rows = np.concatenate([pts, pts])  # two passes
    ref = deployment.reference_rows(rows, 6)
    assert ref.sum() == 12 and np.array_equal(ref[:30], ref[30:])
    chosen = pts[ref[:30]]
    nearest = np.min(np.linalg.norm(chosen[:, None] - chosen[None], axis=2) + np.eye(6) * 9, axis=1)
    assert nearest.min() > 0.25  # far apart, not a cluster
    with pytest.raises(DataError, match="fewer than 5 to score"):
        deployment.reference_rows(pts[:8], 6)
    with pytest.raises(DataError, match="at least 3"):
        deployment.reference_rows(pts, 2)


def test_registration_on_reference_poses_removes_a_new_set_up():
    rng = np.random.default_rng(5)
    commanded = rng.uniform(0.3, 1.0, (40, 3))
    setup = RigidTransform(Rotation.from_rotvec([1e-4, 0, -2e-4]).as_matrix(), np.array([3e-4, -1e-4, 2e-4]))
    measured = setup.apply(commanded) + rng.normal(0, 1e-5, (40, 3))  # the model predicts 0 error here
    residual = commanded - measured
    ref = deployment.reference_rows(commanded, 8)
    reg = deployment.register(measured, residual, ref)
    assert np.sqrt(np.mean(residual ** 2)) > 1e-4
    assert np.sqrt(np.mean(reg.residual[reg.test] ** 2)) < 2e-5
    assert np.all(reg.u[reg.test] > 0) and reg.fit.dof == 3 * ref.sum() - 6


def test_the_effect_parameters_covariance_is_eq17s_u_model_without_a_gp():
    """u_model of a map of effect terms alone is its parameters' covariance through each row's
    regressors (a Sigma a^T), not 0: a geometric map fitted on one UR10 campaign, compared on another."""
    from dt_runtime.analysis.compare import compare
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.models.hybrid import HybridModel
    from tests.support.ur10_generator import generate

    train, test = generate("none", 3, n_points=30, passes=2), generate("none", 53, n_points=20, passes=1, arm_seed=3)
    m = HybridModel(("geometric",), "none", robot=CONFIGS / "robots" / "ur10.yaml").fit(train)
    result, arrays = compare([m], test)
    std = arrays["models"][-1]["std"]
    A = m.design_matrix(test).A
    expected = np.sqrt(np.einsum("nap,pq,naq->na", A, m.theta_cov_, A))
    assert np.all(std > 0) and std == pytest.approx(expected, rel=1e-9)
    assert "Sigma_theta" in result.t_test["u_model"]


def _readings(n=20, seed=4):
    rng = np.random.default_rng(seed)
    return rng.uniform([0.6, -0.4, 0.2], [1.2, 0.4, 0.9], (n, 3)), rng


def test_a_moved_set_up_is_one_rigid_shift():
    P, rng = _readings()
    moved = RigidTransform(Rotation.from_rotvec([2e-4, -1e-4, 3e-4]).as_matrix(), np.array([4e-4, -2e-4, 1e-4]))
    d = moved.apply(P) - P + rng.normal(0, 2e-5, P.shape)
    s = deployment.rigid_shift(P, d, np.full(3, 2e-5))
    assert s.rigid and s.p_before < 1e-6 and s.p_after > 0.01 and "re-reference" in s.text
    assert s.rotation_mrad == pytest.approx([0.2, -0.1, 0.3], abs=0.1)


def test_a_changed_arm_is_not_a_rigid_shift():
    """A joint's zero offset of the arm (the forearm's, as the sim's fault) gives differences that
    change with the pose: not a set-up that moved."""
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.frames.kinematics import load_robot

    chain = load_robot(CONFIGS / "robots" / "ur10.yaml")
    rng = np.random.default_rng(9)
    q = rng.uniform([-1.0, -2.0, -2.0, -2.0, 0.8, -1.0], [1.0, -1.0, -0.8, -0.8, 2.2, 1.0], (20, 6))
    dq = np.zeros(6)
    dq[2] = 5e-4  # 0.5 mrad on joint 3
    P = chain.fk(q)
    d = chain.fk(q + dq) - P + rng.normal(0, 2e-5, P.shape)
    s = deployment.rigid_shift(P, d, np.full(3, 2e-5))
    assert not s.rigid and s.p_before < 1e-6 and "the arm changed" in s.text


def test_readings_within_u_are_no_shift_and_too_few_are_refused():
    P, rng = _readings()
    s = deployment.rigid_shift(P, rng.normal(0, 2e-5, P.shape), np.full(3, 2e-5))
    assert not s.rigid and "no shift" in s.text
    with pytest.raises(DataError, match="at least 6"):
        deployment.rigid_shift(P[:5], P[:5] * 0, np.full(3, 2e-5))


def test_a_low_coverage_on_rows_beyond_the_training_data_is_put_down_to_extrapolation():
    from dt_runtime.analysis import validity
    from dt_runtime.models.effects import Inputs

    rng = np.random.default_rng(1)
    P = rng.uniform(0, 1, (40, 3))
    e = rng.normal(0, 1e-4, (40, 3))
    s = validity.Sample("new_data", "the 40 rows", "errors the instrument measured", e, np.full((40, 3), 5e-5),
                        Inputs(commanded=P), stated="U95 of the prediction",
                        outside_domain="40 of 40 rows lie outside the model's training domain (q1 40)")
    v = validity.assess([s])
    c = v["checks"][0]
    assert v["status"] == "fail" and c["cause"] == "extrapolation beyond the model's training data"
    assert "q1 40" in c["evidence"] and "trained domain" in v["line"]
