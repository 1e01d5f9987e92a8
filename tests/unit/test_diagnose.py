"""Hybrid model and diagnose on simulated data with a known hidden effect (fast version)."""
import numpy as np
import pytest

from dt_runtime.analysis.diagnose import DiagnoseOptions, diagnose
from dt_runtime.reports.verdicts import with_verdict
from dt_runtime.analysis.ranking import gp_alternatives
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.measurements.plans import PlanConfig, doe_points
from dt_runtime.models import effects as fx
from dt_runtime.models.hybrid import HybridModel
from sim.plant import SimulatedCobot
from sim.scenario import Scenario

STIFFNESS = [1.0e6, 5.0e5, 4.0e5, 2.0e5, 2.0e5, 1.0e5]


def collect(effects: dict, reps=2, seed=3):
    scn = Scenario.model_validate({
        "seed": seed, "joint_noise_rad": 5e-6, "dwell_s": 30,
        "payload_schedule": [{"at_s": 0, "kg": 0}, {"at_s": 1500, "kg": 15}, {"at_s": 3000, "kg": 5}],
        "effects": {"geometric": {"enabled": True}, **effects}})
    plant = SimulatedCobot(scn)
    rng = np.random.default_rng(seed)
    pts = doe_points(PlanConfig(registration_speed=1.0))
    rows = []
    for _ in range(reps):
        for i in rng.permutation(len(pts)):
            v = float(rng.choice([0.3, 0.6, 0.9]))
            plant.move_linear(pts[i], v)
            e = plant.controller_tcp() - plant.actual_tcp() + rng.normal(0, 10e-6, 3)  # LT noise
            rows.append((plant.controller_tcp(), plant.joint_angles(), v, plant.payload(), plant.clock.t, i, e))
    C, Q, V, P, T, G, E = (np.array(x) for x in zip(*rows))
    return Dataset(commanded=C, error=E, joints=Q, speed=V, payload=P, t=T, point_id=G)


@pytest.fixture(scope="module")
def chain():
    return load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")


def test_hidden_compliance_is_named_first_and_adding_it_cuts_the_error(chain):
    ds = collect({"compliance": {"enabled": True, "stiffness_nm_per_rad": STIFFNESS}})
    r = with_verdict(diagnose(ds, DiagnoseOptions(effects=("geometric",), gp_inputs="tcp_speed", robot=chain,
                                                  candidates=("compliance", "drift", "dynamic"), folds=4)))
    top = r["ranking"][0]
    assert top["effect"] == "compliance" and top["p_value"] < 0.01
    assert top["rmse_after_mm"] < 0.7 * top["rmse_before_mm"]
    assert "payload" in r["verdict"]


def test_hybrid_model_reports_the_physical_stiffness(chain):
    ds = collect({"compliance": {"enabled": True, "stiffness_nm_per_rad": STIFFNESS}})
    m = HybridModel(("geometric", "compliance"), gp_inputs="none", robot=chain).fit(ds)
    k2 = next(p for p in m.parameters() if p["name"] == "stiffness_q2")
    assert k2["unit"] == "N m/rad" and k2["u"] > 0
    assert k2["value"] == pytest.approx(STIFFNESS[1], rel=0.3)


def test_without_a_hidden_effect_nothing_is_named(chain):
    ds = collect({})
    r = with_verdict(diagnose(ds, DiagnoseOptions(effects=("geometric",), gp_inputs="tcp_speed", robot=chain,
                                                  candidates=("compliance", "drift", "dynamic"), folds=4)))
    assert all(x["p_value"] >= 0.01 or not x["significant"] for x in r["ranking"])
    assert r["verdict"].startswith("No candidate effect")


def test_gp_alternatives_are_the_other_inputs_the_data_has():
    n = 4
    full = fx.Inputs(commanded=np.zeros((n, 3)), joints=np.zeros((n, 6)), speed=np.ones(n))
    no_speed = fx.Inputs(commanded=np.zeros((n, 3)), joints=np.zeros((n, 6)))
    assert gp_alternatives(full, "tcp_speed") == ["joints"]
    assert gp_alternatives(full, "tcp") == ["joints", "tcp_speed"]
    assert gp_alternatives(full, "joints") == ["tcp_speed"]
    assert gp_alternatives(no_speed, "tcp_speed") == ["joints"]
    assert gp_alternatives(fx.Inputs(commanded=np.zeros((n, 3))), "tcp") == []


def test_an_error_that_follows_the_joints_not_the_tcp_asks_for_the_gp_on_joints():
    """Error a smooth function of the joint angles, TCP unrelated to them (as when one region is
    reached in several configurations): the GP on the joints wins and the verdict says so."""
    rng = np.random.default_rng(5)
    n = 240
    q = rng.uniform(-1, 1, (n, 6))
    E = 1e-3 * np.column_stack([np.sin(2 * q[:, 1]), np.cos(2 * q[:, 2]), q[:, 0] * q[:, 3]])
    E += rng.normal(0, 10e-6, (n, 3))
    ds = Dataset(commanded=rng.uniform(0.2, 0.8, (n, 3)), error=E, joints=q, speed=rng.choice([0.3, 0.6], n),
                 point_id=np.arange(n))
    r = with_verdict(diagnose(ds, DiagnoseOptions(gp_inputs="tcp", candidates=("dynamic",), folds=4)))
    g = {x["gp_inputs"]: x for x in r["gp_inputs_ranking"]}
    assert set(g) == {"joints", "tcp_speed"}
    assert g["joints"]["significant"] and g["joints"]["p_value"] < 0.01
    assert g["joints"]["rmse_after_mm"] < 0.3 * g["joints"]["rmse_before_mm"]
    assert not g["tcp_speed"]["significant"]
    assert "--gp-inputs joints" in r["verdict"]
