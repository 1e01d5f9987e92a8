import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dt_kernel.errors import DataError
from dt_runtime.frames.registration import (ResidualStats, RigidTransform, fit_rigid, gl_nominal,
                                     register_instrument, registration_residuals,
                                     reproducibility, three_line_frame)

TRUE = RigidTransform(Rotation.from_euler("xyz", [10, -20, 130], degrees=True).as_matrix(),
                      np.array([2.5, -1.0, 0.3]))


def _rng(seed=0):
    return np.random.default_rng(seed)


def test_transform_algebra_matrix_and_json_round_trip():
    rng = _rng(1)
    A = RigidTransform(Rotation.random(random_state=3).as_matrix(), rng.normal(size=3), 1.3)
    p = rng.normal(size=(5, 3))
    # apply on (3,) and (n,3); matrix is Eq. 3 in homogeneous coordinates
    assert np.allclose(A.apply(p[0]), A.apply(p)[0])
    assert np.allclose((A.matrix @ np.c_[p, np.ones(5)].T).T[:, :3], A.apply(p))
    assert np.allclose(A.compose(TRUE).matrix, A.matrix @ TRUE.matrix)
    assert np.allclose(A.inverse().apply(A.apply(p)), p)
    assert np.allclose(A.compose(A.inverse()).matrix, np.eye(4))
    B = RigidTransform.from_matrix(A.matrix)
    assert B.s == pytest.approx(1.3) and np.allclose(B.R, A.R) and np.allclose(B.t, A.t)
    C = RigidTransform.from_dict(json.loads(json.dumps(A.to_dict())))
    assert np.allclose(C.matrix, A.matrix)
    rot = RigidTransform(Rotation.from_rotvec([0, 0, 0.3]).as_matrix(), np.zeros(3))
    assert rot.rotation_angle_to(RigidTransform.identity()) == pytest.approx(0.3)
    with pytest.raises(DataError):
        RigidTransform.from_matrix(np.diag([1.0, 1.0, -1.0, 1.0]))  # a reflection
    with pytest.raises(ValueError):
        A.R[0, 0] = 5.0  # immutable


def test_kabsch_recovers_a_known_transform_from_noisy_points():
    rng = _rng(2)
    P = rng.uniform(-1, 1, (50, 3))
    Q = TRUE.apply(P) + rng.normal(0, 10e-6, P.shape)
    T = fit_rigid(P, Q)
    assert T.rotation_angle_to(TRUE) < 1e-4 and np.linalg.norm(T.t - TRUE.t) < 1e-4
    assert np.linalg.det(T.R) == pytest.approx(1.0) and T.s == 1.0
    # Eq. 4: the fit is a least-squares minimum; any perturbation increases the SSE
    sse = np.sum((T.apply(P) - Q) ** 2)
    Tp = RigidTransform(Rotation.from_rotvec([1e-5, 0, 0]).as_matrix() @ T.R, T.t)
    assert np.sum((Tp.apply(P) - Q) ** 2) > sse


def test_weights_pick_the_trusted_points():
    rng = _rng(3)
    P = rng.uniform(-1, 1, (20, 3))
    Q = TRUE.apply(P)
    Q[:5] += 0.05  # five outliers
    w = np.r_[np.zeros(5), np.ones(15)]
    T = fit_rigid(P, Q, weights=w)
    assert T.rotation_angle_to(TRUE) < 1e-9 and np.allclose(T.t, TRUE.t)
    with pytest.raises(DataError, match="weights"):
        fit_rigid(P, Q, weights=-w)


def test_umeyama_scale_and_inverse():
    rng = _rng(4)
    P = rng.uniform(-1, 1, (20, 3))
    Q = 1.0002 * P @ TRUE.R.T + TRUE.t
    T = fit_rigid(P, Q, scale=True)
    assert T.s == pytest.approx(1.0002, rel=1e-9)
    assert np.allclose(T.inverse().apply(Q), P, atol=1e-12)


def test_mirrored_points_give_the_best_rotation_not_a_reflection():
    rng = _rng(5)
    P = rng.uniform(-1, 1, (10, 3))
    T = fit_rigid(P, P * [1, 1, -1])
    assert np.linalg.det(T.R) == pytest.approx(1.0)
    # planar data (rank 2) are exactly fitted by a proper rotation
    Pp = P * [1, 1, 0]
    Tq = fit_rigid(Pp, TRUE.apply(Pp))
    assert Tq.rotation_angle_to(TRUE) < 1e-9


@pytest.mark.parametrize("P", [np.outer(np.linspace(0, 1, 5), [1, 2, 3]), np.eye(3)[:2]])
def test_collinear_or_too_few_points_are_refused(P):
    with pytest.raises(DataError, match="non-collinear"):
        fit_rigid(P, P)


def test_nan_is_refused():
    P = np.eye(3) + 1.0
    Q = P.copy()
    Q[1, 2] = np.nan
    with pytest.raises(DataError, match="NaN"):
        fit_rigid(P, Q)


def _three_line_data(T_inst_to_gl, noise, seed, reps=10):
    rng = _rng(seed)
    d = np.tile([0.025, 0.05, 0.075, 0.1], reps)
    gl = [np.outer(d, np.eye(3)[k]) for k in range(3)]
    inst = [T_inst_to_gl.inverse().apply(g) + rng.normal(0, noise, g.shape) for g in gl]
    return d, gl, inst


def test_three_line_frame_recovers_instrument_pose():
    # The instrument sees GL points through TRUE^-1; GL is defined by the moves.
    d, gl, inst = _three_line_data(TRUE, 10e-6, seed=6)
    T = three_line_frame(*inst, d, d, d)
    assert T.rotation_angle_to(TRUE) < 5e-4
    # the GL origin (common start point) in instrument coordinates
    assert np.linalg.norm(T.inverse().t - TRUE.inverse().t) < 20e-6
    res = registration_residuals(T, np.vstack(inst), np.vstack(gl))
    assert np.all(res.std(axis=0, ddof=1) < 20e-6) and np.all(np.abs(res.mean(axis=0)) < 10e-6)
    # noise-free: exact
    d0, gl0, inst0 = _three_line_data(TRUE, 0.0, seed=6, reps=1)
    T0 = three_line_frame(*inst0, d0, d0, d0)
    assert np.allclose(T0.matrix, TRUE.matrix, atol=1e-12)


def test_three_line_frame_orients_lines_by_distance_and_checks_handedness():
    d, gl, inst = _three_line_data(TRUE, 0.0, seed=7, reps=1)
    # point order does not matter, only the distances
    order = np.array([3, 1, 0, 2])
    T = three_line_frame(inst[0][order], *inst[1:], d[order], d, d)
    assert np.allclose(T.matrix, TRUE.matrix, atol=1e-12)
    # a left-handed triad (z moved the wrong way) is refused
    with pytest.raises(DataError, match="right-handed"):
        three_line_frame(inst[0], inst[1], inst[2], d, d, -d)
    with pytest.raises(DataError, match="distances_y"):
        three_line_frame(inst[0], inst[1], inst[2], d, d[:2], d)


def test_register_instrument_both_methods_and_residual_stats():
    d, gl, inst = _three_line_data(TRUE, 20e-6, seed=8)
    p_inst, p_gl = np.vstack(inst), np.vstack(gl)
    p_inst[3] = np.nan  # a lost beam is dropped
    r = register_instrument(p_inst, p_gl)
    assert r.method == "three_line" and r.stats.n == 119 and r.stats.dof == 118
    assert r.transform.rotation_angle_to(TRUE) < 1e-3
    r2 = register_instrument(p_inst, p_gl, method="least_squares")
    assert r2.transform.rotation_angle_to(TRUE) < 1e-3
    assert np.all(r2.stats.std < 30e-6)
    # same result with explicit axes/distances
    axes = np.repeat(["x", "y", "z"], 40)
    r3 = register_instrument(p_inst, p_gl, axes=axes, distances=np.tile(d, 3))
    assert np.allclose(r3.transform.matrix, r.transform.matrix)
    assert np.allclose(gl_nominal(axes, np.tile(d, 3)), p_gl)
    out = json.loads(json.dumps(r.to_dict()))
    assert set(out["residuals"]) == {"x", "y", "z", "n", "dof"}
    with pytest.raises(DataError, match="method"):
        register_instrument(p_inst, p_gl, method="icp")


def test_residual_stats_numbers_and_units():
    e = np.array([[1.0, 0.0, -2.0], [3.0, 0.0, 2.0], [2.0, 0.0, 0.0]]) * 1e-3  # m
    s = ResidualStats.of(e)
    assert s.n == 3 and s.dof == 2
    assert np.allclose(s.mean, [2e-3, 0, 0]) and np.allclose(s.std, [1e-3, 0, 2e-3])
    dd = s.to_dict()
    assert dd["x"] == {"mean_mm": pytest.approx(2.0), "std_mm": pytest.approx(1.0)}
    assert dd["z"]["std_mm"] == pytest.approx(2.0) and dd["n"] == 3 and dd["dof"] == 2
    assert s.to_dict("um")["x"]["mean_um"] == pytest.approx(2000.0)


def test_reproducibility_eq12_on_constructed_data():
    # Two locations, 3 replications each: per-group variances known exactly.
    g = np.array([0, 0, 0, 1, 1, 1, 2])  # group 2 has one replication: no variance, skipped
    v = np.zeros((7, 3))
    v[:3, 0] = [1.0, 2.0, 3.0]  # var 1
    v[3:6, 0] = [0.0, 3.0, 6.0]  # var 9
    v[3:6, 1] = [5.0, 5.0, 5.0] + np.array([-2.0, 0.0, 2.0])  # var 4 (group 0 var 0)
    v[6] = 99.0
    r, dof = reproducibility(v, g)
    assert dof == 4
    assert r == pytest.approx([np.sqrt((1 + 9) / 2), np.sqrt((0 + 4) / 2), 0.0])
    # statistical check
    rng = _rng(9)
    gg = np.repeat(np.arange(4), 10)
    vals = np.c_[rng.normal(0, 3e-6, 40), rng.normal(0, 6e-6, 40) + gg, np.zeros(40)]
    r, dof = reproducibility(vals, gg)
    assert dof == 36 and r[0] == pytest.approx(3e-6, rel=0.3) and r[1] == pytest.approx(6e-6, rel=0.3)
    with pytest.raises(DataError, match="2 or more"):
        reproducibility(vals[:4], np.arange(4))
