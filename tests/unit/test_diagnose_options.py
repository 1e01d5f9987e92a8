"""DiagnoseOptions: a diagnosis's choices checked when the record is made, the error naming the
field, the value and what is allowed."""
from __future__ import annotations

import dataclasses

import pytest

from dt_kernel.errors import ConfigError
from dt_runtime.analysis.options import DiagnoseOptions


@pytest.mark.parametrize("field, value, allowed", [
    ("folds", 1, "an integer >= 2"), ("max_steps", 0, "an integer >= 1"), ("seed", -1, "an integer >= 0"),
    ("alpha", 1.5, "a fraction in (0, 1)"), ("min_explained", 1.0, "a fraction in [0, 1)"),
    ("gp_inputs", "speed", "one of tcp_speed, tcp, joints, none"), ("effects", "geometric", "a sequence of names"),
    ("candidates", ["thermal", 3], "a sequence of names"), ("robot", 7, "a robot YAML's path"),
])
def test_a_bad_field_is_refused_by_name_value_and_what_is_allowed(field, value, allowed):
    with pytest.raises(ConfigError, match="DiagnoseOptions") as e:
        DiagnoseOptions(**{field: value})
    assert e.value.key == field and e.value.value == value and allowed in e.value.allowed


def test_out_needs_the_loop():
    with pytest.raises(ConfigError, match="key 'out'.*fit a model with dt fit"):
        DiagnoseOptions(out="model")
    assert DiagnoseOptions(out="model", auto=True).out == "model"


def test_sequences_are_kept_as_tuples_and_the_record_is_frozen():
    o = DiagnoseOptions(effects=["geometric"], candidates=["thermal"], inputs=["map.yaml"], exclude_sessions=[2])
    assert (o.effects, o.candidates, o.inputs, o.exclude_sessions) == (("geometric",), ("thermal",), ("map.yaml",), (2,))
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.folds = 3  # type: ignore[misc]
    assert dataclasses.replace(o, folds=3).folds == 3
