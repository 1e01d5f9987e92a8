"""The twin's stated uncertainties are typed (Twin.uncertainty), read from twin.json's format 1."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dt_kernel.errors import ModelError
from dt_runtime.twin.twin import StatedUncertainty, TwinUncertainty

# twin.json's "u" object as format_version 1 writes it (json.dumps of jsonable(u, finite_only=False))
FORMAT_1 = """{
  "eq11_tcp_c": {"u": [5e-05, 4e-05, 8e-05], "dof": [40.1, 35.2, Infinity], "U": [0.0001, 8e-05, 0.00016],
                 "k": [2.02, 2.03, 1.96]},
  "eq13_e_lt_hat": {"u": [5e-05, 4e-05, 8e-05], "dof": [40, 35, 50], "U": [1e-4, 8e-5, 1.6e-4], "k": [2, 2, 2]},
  "eq14_e_lt_hat_minus_e_mvs": {"u": [9e-05, 8e-05, 9e-05], "dof": [60, 61, 62], "U": [1.8e-4, 1.6e-4, 1.8e-4],
                                "k": [2, 2, 2]},
  "eq15_e_mvs": {"u": [7e-05, 6e-05, 5e-05], "dof": [30, 31, 32], "U": [1.4e-4, 1.2e-4, 1e-4], "k": [2, 2, 2]},
  "eq16_e_mvs_lt_hat": {"u": [1e-04, 9e-05, 9e-05], "dof": [20, 21, 22], "U": [2e-4, 1.8e-4, 1.8e-4],
                        "k": [2.09, 2.08, 2.07]}
}"""


def test_format_1_reads_into_one_typed_entry_per_equation():
    u = json.loads(FORMAT_1)
    t = TwinUncertainty.from_mapping(u)
    assert isinstance(t.tcp_c, StatedUncertainty)
    assert np.allclose(t.tcp_c.u, [5e-05, 4e-05, 8e-05]) and np.isinf(t.tcp_c.dof[2])
    assert np.allclose(t.e_lt_hat_minus_e_mvs.dof, [60, 61, 62]) and np.allclose(t.e_mvs_lt_hat.k, [2.09, 2.08, 2.07])
    assert {f: getattr(t, f).U.shape for f in TwinUncertainty.KEYS} == {f: (3,) for f in TwinUncertainty.KEYS}
    assert set(TwinUncertainty.KEYS.values()) == set(u)  # every stored entry has its typed field


def test_a_missing_or_malformed_entry_names_it():
    u = json.loads(FORMAT_1)
    del u["eq14_e_lt_hat_minus_e_mvs"]
    with pytest.raises(ModelError, match="eq14_e_lt_hat_minus_e_mvs"):
        TwinUncertainty.from_mapping(u, "m/twin.json")
    u = json.loads(FORMAT_1)
    u["eq11_tcp_c"]["U"] = [1e-4, 1e-4]
    with pytest.raises(ModelError, match=r"m/twin.json: u.eq11_tcp_c: U has shape \(2,\)"):
        TwinUncertainty.from_mapping(u, "m/twin.json")
    u = json.loads(FORMAT_1)
    del u["eq16_e_mvs_lt_hat"]["dof"]
    with pytest.raises(ModelError, match="eq16_e_mvs_lt_hat"):
        TwinUncertainty.from_mapping(u, "m/twin.json")
