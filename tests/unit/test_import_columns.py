"""What a mapped file's columns carry beyond the contract (issue 21, part 6): every numeric column
the mapping does not name is kept beside the rows (`Dataset.extra`, by its name in the file), so
the user's declared effects and the diagnosis read humidity or pressure from a foreign file as
from a contract one; and uncertainty columns stating expanded uncertainties (U95 with k = 2, or a
coverage probability with k from the normal or Student table) are imported as standard ones."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from scipy import stats

from dt_kernel.errors import ConfigError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.dataset import read_table
from dt_runtime.measurements.importer import ImportMapping, import_file, load_mapping
from tests.support.humidity_campaign import K_HUMIDITY, campaign

UR10 = str(CONFIGS / "robots" / "ur10.yaml")
HUMIDITY_YAML = str(CONFIGS / "effects" / "humidity.yaml")

# the humidity campaign as a hall's logger might write it: ';', decimal comma, German names, the
# uncertainties as U95 (k = 2), the air pressure and the operator beside the measurement
RENAME = {"x": "X", "y": "Y", "z": "Z", "t": "Zeit [s]", "ex": "dX", "ey": "dY", "ez": "dZ", "ux": "U95 X",
          "uy": "U95 Y", "uz": "U95 Z", "point_id": "Punkt"}
MAPPING = """\
format_version: 1
separator: ";"
decimal: ","
columns: {x: X, y: Y, z: Z, joints: [q1, q2, q3, q4, q5, q6], ex: dX, ey: dY, ez: dZ, point_id: Punkt,
          ux: U95 X, uy: U95 Y, uz: U95 Z}
uncertainty: {kind: expanded, k: 2}
time: {source: seconds, column: "Zeit [s]"}
"""


def _foreign(tmp_path):
    """The contract file, its foreign copy and the mapping that reads it."""
    contract = campaign(tmp_path / "humidity.csv")
    ds = read_table(contract)
    rng = np.random.default_rng(8)
    pressure = 1013.0 + np.cumsum(rng.normal(0, 0.4, ds.n))
    lines = contract.read_text().splitlines()
    head = lines[0].split(",")
    cols = [c for c in head if c not in ("speed", "temperature", "payload", "rep", "mx", "my", "mz")]
    out = [";".join([RENAME.get(c, c) for c in cols] + ["Luftdruck [hPa]", "Bediener"])]
    for i, line in enumerate(lines[1:]):
        cell = dict(zip(head, line.split(",")))
        vals = [str(2 * float(cell[c])) if c in ("ux", "uy", "uz") else cell[c] for c in cols]  # U = 2 u
        out.append(";".join(v.replace(".", ",") for v in vals) + f";{pressure[i]:.2f}".replace(".", ",")
                   + (";Müller" if i % 3 else ";Schmidt"))
    (tmp_path / "hall.csv").write_text("\n".join(out) + "\n", encoding="utf-8")
    (tmp_path / "hall.yaml").write_text(MAPPING, encoding="utf-8")
    return ds, pressure, tmp_path / "hall.csv", tmp_path / "hall.yaml"


def test_every_numeric_column_outside_the_mapping_is_kept_by_its_name(tmp_path, caplog):
    ds, pressure, data, mapping = _foreign(tmp_path)
    with caplog.at_level(logging.WARNING):
        got, rep = import_file(data, mapping)
    assert sorted(got.extra) == ["Luftdruck [hPa]", "fixture_temp", "humidity"]
    np.testing.assert_array_equal(got.extra["humidity"], ds.extra["humidity"])
    np.testing.assert_allclose(got.extra["Luftdruck [hPa]"], pressure, atol=0.005)
    np.testing.assert_allclose(got.error, ds.error, atol=1e-12)
    # the text column is left out, and said once: one warning, one note
    said = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert len(said) == 1 and "Bediener" in said[0]
    assert [n for n in rep.notes if "left out" in n] == ["non-numeric column(s) left out (not named by the "
                                                         "mapping): Bediener"]
    assert any("kept beside the rows: humidity, fixture_temp, Luftdruck [hPa]" in n for n in rep.notes)


def test_rows_the_import_reorders_or_drops_take_their_extra_cells_along(tmp_path):
    header = "Zeit;X;Y;Z;dX;dY;dZ;Feuchte"
    rows = ["0;1;2;3;0,1;0;0;40,5", "20;1;2;3;0,2;0;0;42,5", "10;1;2;3;0,3;0;0;41,5", "30;1;2;3;kaputt;0;0;43,5",
            "40;1;2;3;0,5;0;0;"]
    (tmp_path / "f.csv").write_text(header + "\n" + "\n".join(rows) + "\n", encoding="utf-8")
    m = ImportMapping.model_validate({"separator": ";", "decimal": ",",
                                      "columns": {"x": "X", "y": "Y", "z": "Z", "ex": "dX", "ey": "dY", "ez": "dZ"},
                                      "time": {"source": "seconds", "column": "Zeit", "order": "sort"}})
    ds, _ = import_file(tmp_path / "f.csv", m, skip_bad=True)
    # sorted by time, the bad row skipped, the empty cell NaN: each value stays with its row
    np.testing.assert_allclose(ds.error[:, 0] * 1e3, [0.1, 0.3, 0.2, 0.5])
    np.testing.assert_array_equal(ds.extra["Feuchte"], [40.5, 41.5, 42.5, np.nan])


def test_a_declared_effect_reads_its_column_from_a_mapped_file(tmp_path, capsys):
    _, _, data, mapping = _foreign(tmp_path)
    rc = main(["fit", "--data", str(data), "--mapping", str(mapping), "--robot", UR10, "--effects",
               "geometric,humidity", "--effects-file", HUMIDITY_YAML, "--gp-inputs", "none", "--out",
               str(tmp_path / "m"), "--json", "--no-progress"])
    r = json.loads(capsys.readouterr().out)
    assert rc == 0, r
    got = [p for p in r["parameters"] if p["effect"] == "humidity"]
    for p, k in zip(got, K_HUMIDITY):
        assert p["unit"] == "m/%" and abs(p["value"] - k) < 0.1 * abs(k), (p, k)


def test_expanded_uncertainties_are_divided_by_their_coverage_factor(tmp_path):
    ds, _, data, mapping = _foreign(tmp_path)
    m = load_mapping(mapping)
    got, rep = import_file(data, m)
    np.testing.assert_allclose(got.u, ds.u, rtol=1e-12)  # U95 = 2 u in the file, u on import
    assert rep.to_dict()["uncertainty"] == {"stated": "expanded", "k": 2.0, "coverage": None, "dof": None,
                                            "k_from": "stated", "columns": ["U95 X", "U95 Y", "U95 Z"]}
    assert any("expanded uncertainties: divided by k = 2 (stated)" in n for n in rep.notes)
    # a stated coverage probability: k from the normal distribution, or Student's t with the dof
    for spec, k in (({"coverage": 0.95}, stats.norm.ppf(0.975)), ({"coverage": 0.95, "dof": 8}, stats.t.ppf(0.975, 8)),
                    ({"coverage": 0.99}, stats.norm.ppf(0.995))):
        got, rep = import_file(data, m.model_copy(update={"uncertainty": m.uncertainty.model_validate(
            {"kind": "expanded"} | spec)}))
        np.testing.assert_allclose(got.u, 2 * ds.u / k, rtol=1e-12)
        assert rep.to_dict()["uncertainty"]["k"] == pytest.approx(k, rel=1e-12)
    # standard (the default, the contract's meaning): taken as they are
    got, rep = import_file(data, m.model_copy(update={"uncertainty": m.uncertainty.model_validate({})}))
    np.testing.assert_allclose(got.u, 2 * ds.u, rtol=1e-12)
    assert rep.to_dict()["uncertainty"]["stated"] == "standard"


@pytest.mark.parametrize("spec,message", [
    ("{kind: expanded}", "needs one of k"),
    ("{kind: expanded, k: 2, coverage: 0.95}", "not both"),
    ("{k: 2}", "set kind: expanded"),
    ("{kind: expanded, k: 2, dof: 9}", "dof goes with coverage"),
    ("{kind: expanded, k: 0.5}", "greater than or equal to 1"),
    ("{kind: expanded, coverage: 95}", "less than 1"),
])
def test_a_bad_uncertainty_key_names_what_is_wrong(tmp_path, spec, message):
    (tmp_path / "m.yaml").write_text(MAPPING.replace("{kind: expanded, k: 2}", spec), encoding="utf-8")
    with pytest.raises(ConfigError, match=message) as e:
        load_mapping(tmp_path / "m.yaml")
    assert "uncertainty" in str(e.value)


def test_expanded_without_uncertainty_columns_is_refused(tmp_path):
    (tmp_path / "m.yaml").write_text(MAPPING.replace("          ux: U95 X, uy: U95 Y, uz: U95 Z}", "}")
                                     .replace("point_id: Punkt,", "point_id: Punkt"), encoding="utf-8")
    with pytest.raises(ConfigError, match="does not name"):
        load_mapping(tmp_path / "m.yaml")
