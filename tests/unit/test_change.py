"""A model's change in `dt diagnose --auto`: typed inside the code, shown by the labels the JSON
keys `change` and `added` have always carried."""
from __future__ import annotations

import pytest

from dt_runtime.analysis.change import Change
from dt_runtime.analysis.selection import Step


@pytest.mark.parametrize("kind, name, label", [
    ("effect", "backlash", "+backlash"), ("remove", "thermal", "-thermal"), ("gp_inputs", "joints", "GP -> joints"),
    ("session", "tool", "+session tool"),
])
def test_the_label_is_the_json_string_and_reads_back_to_the_same_change(kind, name, label):
    c = Change(kind, name)
    assert c.label() == str(c) == label
    assert Change.parse(label) == c


def test_a_bad_kind_or_label_is_refused():
    with pytest.raises(ValueError, match="Change.kind: 'add'"):
        Change("add", "backlash")  # type: ignore[arg-type]
    for text in ("backlash", "+", "GP -> ", ""):
        with pytest.raises(ValueError, match="not a change's label"):
            Change.parse(text)


def test_a_step_writes_its_change_as_the_label():
    step = Step("GP(TCP, v)", {}, 1.0, 0.1, 1.2, "regions", Change("session", "tool"), 1e-4, 0.3, 0.01)
    assert step.to_dict()["change"] == "+session tool"
    step.change = None
    assert step.to_dict()["change"] is None
