"""The compiled kernels of the correction law's hot path (`common.jit`, numba) give the numbers of
the code they stand in for: the GP's mean and kernel vectors (`FastPredictor.mean_kernel`), the
warm-started IK (`NewtonIK` on plain floats, the same steps and the same UnreachableError), and the
plain law's U to its own rounding; without numba (DT_NO_JIT) the numpy path runs."""
import os
import subprocess
import sys

import numpy as np
import pytest

from dt_kernel.errors import UnreachableError
from dt_runtime.common import jit
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.frames.newton_ik import NewtonIK
from dt_runtime.models.gp_kernel import GPArrays, gp_mean
from dt_runtime.twin.corrector import Corrector
from dt_runtime.twin.twin import Twin
from tests.support.reference_correction import ReferenceCorrector

needs_jit = pytest.mark.skipif(not jit.enabled(), reason="numba is not installed: the numpy path is all there is")


@needs_jit
def test_the_gp_kernel_is_the_predictors_mean_and_kernel_vectors(twin_dir):
    p = Twin.load(twin_dir).e_lt.gp_.predictor()
    a = GPArrays(p)
    rng = np.random.default_rng(0)
    for x in np.column_stack([rng.uniform(0.7, 1.1, 20), rng.uniform(-0.2, 0.2, 20), rng.uniform(0.4, 0.7, 20),
                              rng.uniform(0.05, 1.0, 20)]):
        m, K = p.mean_kernel(x)
        gp_mean(x, a.Xb, a.xm, a.xs, a.nh, a.sf2, a.m0, a.ys, a.alpha, a.z, a.acc, a.K, a.m)
        assert a.m == pytest.approx(m, rel=1e-12, abs=1e-15)  # m: 1e-12 mm
        assert a.K == pytest.approx(K, rel=1e-13, abs=1e-300)


@needs_jit
@pytest.mark.parametrize("robot", ["cobot_hc20_like.yaml", "ur10.yaml", "catalogue/panda.yaml", "catalogue/iiwa7.yaml"])
def test_the_compiled_ik_takes_the_same_steps_as_on_plain_floats(robot):
    chain = load_robot(CONFIGS / "robots" / robot)
    fast, floats = NewtonIK(chain), NewtonIK(chain, compiled=False)
    assert fast._k is not None and floats._k is None
    rng = np.random.default_rng(1)
    q0 = rng.uniform(-0.8, 0.8, chain.dof)
    p0 = fast.pose(q0)[0]
    qa = qb = q0
    for k in range(60):  # a path of 1 mm steps, each solve seeded with the previous solution
        x = p0 + 1e-3 * k * np.array([0.6, -0.8, 0.3])
        qa, qb = fast.solve(x, qa), floats.solve(x, qb)
        assert qa == pytest.approx(qb, abs=1e-12) and fast.iterations == floats.iterations
    for ik in (fast, floats):
        with pytest.raises(UnreachableError, match="no joint angles of"):
            ik.solve(p0 + np.array([10.0, 0.0, 0.0]), q0)


def test_the_plain_laws_U_moves_by_more_than_1e_12_m_when_its_input_moves_by_one_ulp(twin_dir):
    """Why the compiled law's U is held to the plain law's at 1e-11 m, not 1e-12
    (tests/unit/test_corrector.py, U_ROUNDING): the plain law is not resolved finer than that."""
    ref = ReferenceCorrector(Twin.load(twin_dir))
    x = np.array([0.91, 0.01, 0.56])
    base = ref.correct(x, 0.3).U
    moved = max(np.abs(ref.correct(np.nextafter(x, x + s), 0.3).U - base).max() for s in (-1.0, 1.0))
    assert 1e-13 < moved < 1e-11, moved


@needs_jit
def test_the_compiled_law_is_the_numpy_path(twin_dir):
    twin = Twin.load(twin_dir)
    fast, slow = Corrector(twin), Corrector(twin, compiled=False)
    assert fast.compiled and not slow.compiled
    rng = np.random.default_rng(2)
    prev = None
    for x in np.array([0.9, 0.0, 0.55]) + np.cumsum(rng.uniform(-2e-4, 2e-4, (100, 3)), axis=0):
        a, b = fast.correct(x, 0.3, warm=prev), slow.correct(x, 0.3, warm=prev)
        assert a.command == pytest.approx(b.command, abs=1e-12)
        assert a.U == pytest.approx(b.U, abs=1e-11) and a.inside == b.inside
        prev = a.command - x
    assert fast.evaluations == slow.evaluations


def test_without_numba_the_numpy_path_runs(twin_dir):
    code = ("import numpy as np\nfrom dt_runtime.common import jit\nfrom dt_runtime.twin.corrector import Corrector\n"
            "from dt_runtime.twin.twin import Twin\n"
            f"c = Corrector(Twin.load({str(twin_dir)!r}))\n"
            "print(jit.enabled(), c.compiled, c.correct(np.array([0.9, 0.0, 0.55]), 0.3).command.tolist())")
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, jit.ENV: "1"}, capture_output=True,
                         text=True, check=True).stdout.split(maxsplit=2)
    assert out[:2] == ["False", "False"]
    ref = ReferenceCorrector(Twin.load(twin_dir)).correct(np.array([0.9, 0.0, 0.55]), 0.3).command
    assert np.array(eval(out[2])) == pytest.approx(ref, abs=1e-12)


def test_eq17_reads_the_same_means_without_the_std(twin_dir):
    """`Twin.predicted_means` (the monitor's) is e_lt_hat's and e_mvs_lt_hat's mean, to the bit."""
    twin = Twin.load(twin_dir)
    rng = np.random.default_rng(6)
    for c in np.array([0.9, 0.0, 0.55]) + rng.uniform(-0.2, 0.2, (10, 3)):
        e_lt, e_mvs = twin.predicted_means(c, 0.4)
        assert np.array_equal(e_lt, twin.e_lt_hat(c, 0.4)[0]) and np.array_equal(e_mvs, twin.e_mvs_lt_hat(c, 0.4)[0])


@pytest.mark.parametrize("compiled", [False, True])
def test_the_command_only_is_the_laws_command(twin_dir, compiled):
    """`correct(..., uncertainty=False)` (what `follow` streams) gives the same command and volume
    flag, U and sigma NaN."""
    c = Corrector(Twin.load(twin_dir), compiled=compiled)
    for x in np.array([0.9, 0.0, 0.55]) + np.random.default_rng(7).uniform(-0.2, 0.2, (10, 3)):
        full, bare = c.correct(x, 0.3), c.correct(x, 0.3, uncertainty=False)
        assert np.array_equal(full.command, bare.command) and full.inside == bare.inside
        assert np.isnan(bare.U).all() and np.isnan(bare.sigma).all() and np.isfinite(full.U).all()
