import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dt_runtime.errors import DataError
from dt_runtime.registration import (RigidTransform, fit_rigid, registration_residuals,
                                     reproducibility, three_line_frame)

RNG = np.random.default_rng(0)
TRUE = RigidTransform(Rotation.from_euler("xyz", [10, -20, 130], degrees=True).as_matrix(),
                      np.array([2.5, -1.0, 0.3]))


def test_kabsch_recovers_a_known_transform_from_noisy_points():
    P = RNG.uniform(-1, 1, (50, 3))
    Q = TRUE.apply(P) + RNG.normal(0, 10e-6, P.shape)
    T = fit_rigid(P, Q)
    ang = np.linalg.norm(Rotation.from_matrix(T.R @ TRUE.R.T).as_rotvec())
    assert ang < 1e-4 and np.linalg.norm(T.t - TRUE.t) < 1e-4
    assert np.linalg.det(T.R) == pytest.approx(1.0)


def test_umeyama_scale_and_inverse():
    P = RNG.uniform(-1, 1, (20, 3))
    Q = 1.0002 * P @ TRUE.R.T + TRUE.t
    T = fit_rigid(P, Q, scale=True)
    assert T.s == pytest.approx(1.0002, rel=1e-9)
    assert np.allclose(T.inverse().apply(Q), P, atol=1e-12)


def test_mirrored_points_still_give_a_rotation():
    P = RNG.uniform(-1, 1, (10, 3))
    T = fit_rigid(P, P * [1, 1, -1])
    assert np.linalg.det(T.R) == pytest.approx(1.0)


def test_collinear_points_are_refused():
    P = np.outer(np.linspace(0, 1, 5), [1, 2, 3])
    with pytest.raises(DataError, match="non-collinear"):
        fit_rigid(P, P)


def test_three_line_frame_recovers_instrument_pose():
    # Instrument sees GL points through TRUE^-1; GL is defined by the moves.
    d = np.tile([0.025, 0.05, 0.075, 0.1], 10)
    gl = [np.outer(d, np.eye(3)[k]) for k in range(3)]
    inst = [TRUE.inverse().apply(g) + RNG.normal(0, 10e-6, g.shape) for g in gl]
    T = three_line_frame(*inst, d, d, d)
    res = registration_residuals(T, np.vstack(inst), np.vstack(gl))
    assert np.max(np.abs(res.std(axis=0))) < 20e-6
    ang = np.linalg.norm(Rotation.from_matrix(T.R @ TRUE.R.T).as_rotvec())
    assert ang < 5e-4


def test_reproducibility_eq12():
    g = np.repeat(np.arange(4), 10)
    vals = np.zeros((40, 3))
    vals[:, 0] = RNG.normal(0, 3e-6, 40)
    vals[:, 1] = RNG.normal(0, 6e-6, 40) + g
    r, dof = reproducibility(vals, g)
    assert dof == 36
    assert r[0] == pytest.approx(3e-6, rel=0.3) and r[1] == pytest.approx(6e-6, rel=0.3) and r[2] == 0
