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
