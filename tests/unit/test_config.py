import pytest
from pydantic import ValidationError

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import ConfigError


class Inner(Frozen):
    stiffness: float


class Outer(Frozen):
    name: str
    joint: Inner


def test_unknown_key_names_file_key_and_allowed(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("name: a\njoint: {stiffness: 1.0, stiffnes: 2}\n")
    with pytest.raises(ConfigError) as ei:
        load_yaml(p, Outer)
    msg = str(ei.value)
    assert "c.yaml" in msg and "joint.stiffnes" in msg and "stiffness" in msg


def test_config_is_frozen(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("name: a\njoint: {stiffness: 1.0}\n")
    cfg = load_yaml(p, Outer)
    with pytest.raises(ValidationError, match="frozen"):
        cfg.name = "b"


def test_exponent_without_sign_is_a_float(tmp_path):
    from dt_kernel.config import read_yaml

    p = tmp_path / "c.yaml"
    p.write_text("a: 1.0e6\nb: 1e-5\nc: 3\nd: '1e3'\n")
    d = read_yaml(p)
    assert d == {"a": 1.0e6, "b": 1e-5, "c": 3, "d": "1e3"}
