"""The effect registry is the one place that lists the model's effects: its names are the
simulator's (docs/effects.md: the names are a contract), every effect declares what it needs, and what it declares
is what it does (availability, errors, regressor shapes)."""
import numpy as np
import pytest

from dt_kernel.errors import DataError
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.models import effects as fx
from dt_runtime.models.effects.base import Effect
from sim.scenario import EFFECTS as SIM_EFFECTS

CONTRACT = ("geometric", "compliance", "gear", "backlash", "thermal", "dynamic", "drift")


@pytest.fixture(scope="module")
def chain():
    return load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")


def full_inputs(n=12, seed=0):
    rng = np.random.default_rng(seed)
    return fx.Inputs(commanded=rng.uniform(0.3, 0.8, (n, 3)), joints=rng.uniform(-1, 1, (n, 6)),
                     speed=rng.choice([0.1, 0.3], n), temperature=rng.uniform(19, 25, n),
                     payload=rng.choice([0.0, 5.0], n), t=np.sort(rng.uniform(0, 7200, n)))


def test_model_effects_are_the_simulators_and_the_contracts():
    assert fx.names() == tuple(SIM_EFFECTS) == CONTRACT


def test_every_effect_declares_what_it_needs():
    inputs = set(fx.Inputs.__dataclass_fields__)
    for name, e in fx.REGISTRY.items():
        assert isinstance(e, Effect) and e.name == name
        assert e.columns and set(e.columns) <= inputs, name
        assert isinstance(e.needs_chain, bool)
        assert isinstance(e.factor, str) and len(e.factor) > 10, name
    assert {n for n, e in fx.REGISTRY.items() if not e.needs_chain} == {"thermal", "dynamic"}


@pytest.mark.parametrize("name", CONTRACT)
def test_each_block_has_one_name_and_unit_per_parameter(name, chain):
    inp = full_inputs()
    b = fx.build(name, inp, chain)
    assert b.effect == name
    assert b.A.shape[:2] == (inp.n, 3) and b.A.shape[2] == len(b.names) == len(b.units) > 0
    assert np.all(np.isfinite(b.A))


@pytest.mark.parametrize("name", CONTRACT)
def test_available_and_build_agree_on_missing_columns_and_chain(name, chain):
    e = fx.get(name)
    inp = full_inputs()
    assert name in fx.available(inp, chain)
    without = fx.Inputs(**{f: (None if f == e.columns[-1] else getattr(inp, f))
                           for f in fx.Inputs.__dataclass_fields__})
    assert name not in fx.available(without, chain)
    with pytest.raises(DataError, match=f"'{name}' needs the column"):
        fx.build(name, without, chain)
    assert (name in fx.available(inp, None)) == (not e.needs_chain)
    if e.needs_chain:
        with pytest.raises(DataError, match="kinematic model \\(parameter robot\\)") as err:
            fx.build(name, inp, None)
        assert "--" not in str(err.value)  # a library names its parameter, not a CLI flag


def test_thermal_is_expansion_from_20_C():
    inp = full_inputs()
    b = fx.build("thermal", inp, None)
    alpha = 2.3e-5
    np.testing.assert_allclose(b.A[:, :, 0] * alpha, -alpha * (inp.temperature - 20.0)[:, None] * inp.commanded)


def test_unknown_names_are_refused_all_at_once():
    with pytest.raises(DataError, match="unknown effect\\(s\\) backlesh, termal; known: geometric"):
        fx.check_names(("backlash", "backlesh", "termal"))
