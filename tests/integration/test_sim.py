"""The simulated plant: exact controller kinematics, each physical effect behaving physically."""
import numpy as np
import pytest

from dt_kernel.errors import ConfigError, UnreachableError
from sim.kinematics import Arm
from sim.plant import SimulatedCobot
from sim.scenario import Scenario, load_scenario

TARGET = np.array([0.9, 0.1, 0.5])


def scenario(**effects) -> Scenario:
    eff = {name: {"enabled": True, **cfg} for name, cfg in effects.items()}
    return Scenario.model_validate({"seed": 1, "joint_noise_rad": 0.0, "effects": eff})


def error_at(plant, target, speed=0.5):
    plant.move_linear(np.asarray(target), speed)
    return plant.controller_tcp() - plant.actual_tcp()


@pytest.fixture(scope="module")
def arm():
    a = Arm()
    yield a
    a.close()


def test_ik_is_exact_to_a_fraction_of_the_resolution(arm):
    rng = np.random.default_rng(0)
    for _ in range(20):
        tgt = np.array([0.9, 0.0, 0.55]) + rng.uniform(-1, 1, 3) * [0.5, 0.4, 0.35]
        q = arm.ik(tgt)
        assert np.linalg.norm(arm.fk(q)[0] - tgt) < 3e-7


def test_unreachable_target_is_reported(arm):
    with pytest.raises(UnreachableError, match="out of reach"):
        arm.ik(np.array([3.0, 0.0, 0.5]))


def test_no_effects_no_noise_means_no_error():
    p = SimulatedCobot(scenario())
    assert np.max(np.abs(error_at(p, TARGET))) < 1e-6  # within the 1 um resolution


def test_compliance_grows_with_payload():
    light = SimulatedCobot(scenario(compliance={}).model_copy(update={"payload_kg": 0.0}))
    heavy = SimulatedCobot(scenario(compliance={}).model_copy(update={"payload_kg": 20.0}))
    e0, e20 = error_at(light, TARGET), error_at(heavy, TARGET)
    # Gravity bends the arm down: measured below commanded, so e_z = cmd - meas > 0.
    assert e20[2] > e0[2] > 0
    assert np.linalg.norm(e20) > 1.5 * np.linalg.norm(e0)


def test_backlash_depends_on_direction_of_approach():
    p = SimulatedCobot(scenario(backlash={}))
    error_at(p, TARGET + [0.1, 0.1, 0.1])
    from_above = error_at(p, TARGET)
    error_at(p, TARGET - [0.1, 0.1, 0.1])
    from_below = error_at(p, TARGET)
    assert np.linalg.norm(from_above - from_below) > 2e-5


def test_dynamic_error_scales_with_speed():
    p = SimulatedCobot(scenario(dynamic={"lag_s": 0.0, "sag_s": 2e-4}))
    slow = error_at(p, TARGET, 0.2)
    fast = error_at(p, TARGET, 0.8)
    assert fast[2] == pytest.approx(4 * slow[2], rel=0.05)


def test_thermal_expansion_follows_temperature():
    scn = Scenario.model_validate({"seed": 1, "joint_noise_rad": 0.0, "temperature": {"base_c": 30.0},
                                   "effects": {"thermal": {"enabled": True}}})
    e = error_at(SimulatedCobot(scn), TARGET)
    # 10 K above reference, 23e-6/K: the arm reaches 230 ppm further from its base.
    assert np.allclose(-e, TARGET * 23e-6 * 10, atol=2e-6)


def test_the_structure_lags_the_air_temperature():
    # the air ramps 10 K/h from the 20 C reference; the structure follows with a 30 min lag
    scn = Scenario.model_validate({"seed": 1, "joint_noise_rad": 0.0, "dwell_s": 600.0,
                                   "temperature": {"base_c": 20.0, "ramp_c_per_h": 10.0, "amplitude_c": 0.0},
                                   "effects": {"thermal": {"enabled": True, "lag_s": 1800.0}}})
    p = SimulatedCobot(scn)
    for _ in range(12):  # about 2 h of moves and dwells
        error_at(p, TARGET)
    air, structure = p.temperature(), p.structure_temperature()
    # a ramp r through a first-order lag tau: the structure trails by r tau (1 - exp(-t/tau))
    h = p.clock.t / 3600
    assert structure == pytest.approx(air - 5.0 * (1 - np.exp(-h / 0.5)), abs=1e-6)
    e = error_at(p, TARGET)  # the expansion follows the structure, not the air
    assert np.allclose(-e, TARGET * 23e-6 * (p.structure_temperature() - 20.0), atol=2e-6)


def test_drift_grows_with_time():
    p = SimulatedCobot(scenario(drift={}).model_copy(update={"dwell_s": 1800.0}))
    e1 = error_at(p, TARGET)
    for _ in range(4):
        e2 = error_at(p, TARGET)
    assert np.linalg.norm(e2) > 2 * np.linalg.norm(e1)


def test_same_seed_same_numbers():
    scn = load_scenario("configs/scenarios/paper_default.yaml")
    a, b = SimulatedCobot(scn), SimulatedCobot(scn)
    assert np.array_equal(error_at(a, TARGET), error_at(b, TARGET))


def test_default_scenario_reproduces_table3_scale():
    p = SimulatedCobot(load_scenario("configs/scenarios/paper_default.yaml"))
    rng = np.random.default_rng(3)
    e = np.array([error_at(p, np.array([0.9, 0, 0.55]) + rng.uniform(-1, 1, 3) * [0.5, 0.3, 0.35])
                  for _ in range(150)])
    s = e.std(axis=0) * 1e3
    # Paper Table 3: s(e_LT) = 0.816 / 0.479 / 0.331 mm. Same scale, same ordering.
    assert 0.5 < s[0] < 1.1 and 0.25 < s[1] < 0.7 and 0.15 < s[2] < 0.5
    assert s[0] > s[1] > s[2]


def test_negative_stiffness_is_refused_naming_file_key_value(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("effects:\n  compliance:\n    enabled: true\n"
                 "    stiffness_nm_per_rad: [1.0e6, -5.0e5, 4.0e5, 2.0e5, 2.0e5, 1.0e5]\n")
    with pytest.raises(ConfigError) as ei:
        load_scenario(f)
    msg = str(ei.value)
    assert "bad.yaml" in msg and "effects.compliance.stiffness_nm_per_rad" in msg and "-500000" in msg
    assert "> 0" in msg


def test_unknown_effect_key_lists_known(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("effects:\n  gravity: {enabled: true}\n")
    with pytest.raises(ConfigError) as ei:
        load_scenario(f)
    assert "effects.gravity" in str(ei.value) and "compliance" in str(ei.value)
