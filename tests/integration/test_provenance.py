"""The traceability record (dt_runtime.common.provenance): its fields, file hashes that follow
the file, the record in a model saved by `dt fit` (version, commit, the data file's SHA-256),
old models without it still load, `dt compare`/`dt diagnose` JSON and the reports carry it, the
quick demo's summary hashes its configs, and the instruments YAML fails with clear errors."""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import platform
from datetime import datetime, timedelta

import numpy as np
import pytest

from dt_kernel.errors import ConfigError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.common.provenance import (
    CHUNK,
    Environment,
    FileRecord,
    Provenance,
    build,
    load_instruments,
    sha256_file,
)
from dt_runtime.common.version import git_commit, version
from dt_runtime.measurements.dataset import Dataset, write_table
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.reports.demo_report import build_demo_report
from dt_runtime.workflows.demo import DemoResult

ROBOT = CONFIGS / "robots" / "cobot_hc20_like.yaml"
EXAMPLE = CONFIGS / "instruments_example.yaml"


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_json(argv: list[str]) -> tuple[int, dict]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main([*argv, "--json", "--no-progress"])
    return rc, json.loads(buf.getvalue())


@pytest.fixture(scope="module")
def data_csv(tmp_path_factory):
    rng = np.random.default_rng(4)
    n = 80
    P = rng.uniform([0.4, -0.3, 0.3], [0.9, 0.3, 0.8], (n, 3))
    E = 1e-3 * np.column_stack([np.sin(3 * P[:, 0]), np.cos(2 * P[:, 1]), P[:, 2]]) + rng.normal(0, 2e-5, (n, 3))
    ds = Dataset(commanded=P, error=E, speed=rng.choice([0.1, 0.3], n), temperature=np.linspace(20.0, 22.5, n),
                 t=np.linspace(0, 3600, n), point_id=np.arange(n) // 2)
    return write_table(ds, tmp_path_factory.mktemp("data") / "campaign.csv")


@pytest.fixture(scope="module")
def fitted(data_csv, tmp_path_factory):
    out = tmp_path_factory.mktemp("models") / "m"
    rc, res = run_json(["fit", "--data", str(data_csv), "--out", str(out), "--gp-inputs", "none",
                        "--effects", "thermal", "--instruments", str(EXAMPLE)])
    assert rc == 0, res
    return out, res


# --------------------------------------------------------------------------- the record

def test_the_record_has_software_time_inputs_robot_instruments_and_environment(tmp_path):
    f = tmp_path / "in.txt"
    f.write_text("abc")
    rec = build([f, f, tmp_path / "missing.csv"], robot=ROBOT, instruments=load_instruments(EXAMPLE),
                temperature=[20.0, 21.0, float("nan"), 22.0])
    d = rec.to_dict()
    assert set(d) == {"schema", "software", "created", "python", "inputs", "robot", "instruments", "environment"}
    assert d["software"] == {"name": "cobot-dt", "version": version(), "commit": git_commit()}
    created = datetime.fromisoformat(d["created"])
    assert created.utcoffset() == timedelta(0)
    assert d["python"] == platform.python_version()
    assert d["inputs"] == [{"path": str(f.resolve()), "sha256": sha(f), "size_bytes": 3}]  # once; missing skipped
    assert d["robot"]["path"] == "configs/robots/cobot_hc20_like.yaml" and d["robot"]["sha256"] == sha(ROBOT)
    tracker = next(i for i in d["instruments"] if i["role"] == "tracker")
    assert tracker["certificate"] and tracker["serial"] and tracker["calibration_date"] == "2026-01-15"
    assert tracker["uncertainty"]["kind"] == "MPE"
    assert tracker["uncertainty"]["terms"]["per_length"] == {"value": 6.0, "unit": "um/m"}
    assert d["environment"] == {"temperature_c": {"min": 20.0, "max": 22.0, "mean": 21.0, "n": 3}}
    assert Provenance.from_dict(json.loads(json.dumps(d))) == rec
    assert build(robot_name="ur10").robot.to_dict() == {"name": "ur10", "path": None, "sha256": None}
    assert Environment.of(None) is None and Environment.of([float("nan")]) is None


def test_the_hash_follows_the_file_and_is_read_in_chunks(tmp_path):
    f = tmp_path / "big.bin"
    f.write_bytes(bytes(range(256)) * (CHUNK // 256 * 2 + 7))  # more than two chunks
    before = FileRecord.of(f)
    assert before.sha256 == sha(f) and before.size_bytes == f.stat().st_size
    with open(f, "r+b") as fh:  # one byte changed, same size
        fh.seek(CHUNK + 3)
        fh.write(b"\xff")
    assert sha256_file(f) == sha(f) != before.sha256


# --------------------------------------------------------------------------- models and results

def test_a_model_saved_by_dt_fit_records_version_commit_and_the_data_hash(fitted, data_csv):
    out, res = fitted
    meta = json.loads((out / "hybrid.json").read_text())
    p = meta["provenance"]
    assert p["software"]["version"] == version()
    commit = git_commit()
    if commit is not None:  # run from a git checkout
        assert p["software"]["commit"] == commit and len(commit.split("-")[0]) == 40
    files = {f["path"]: f for f in p["inputs"]}
    rec = files[str(data_csv.resolve())]
    assert rec["sha256"] == sha(data_csv) and rec["size_bytes"] == data_csv.stat().st_size
    assert files["configs/instruments_example.yaml"]["sha256"] == sha(EXAMPLE)
    assert p["robot"]["sha256"] == sha(ROBOT)
    assert {i["role"] for i in p["instruments"]} == {"tracker", "camera", "thermometer"}
    assert p["environment"]["temperature_c"]["min"] == pytest.approx(20.0)
    assert p["environment"]["temperature_c"]["max"] == pytest.approx(22.5)
    assert res["provenance"] == p  # `dt fit --json` states the record it saved
    assert HybridModel.load(out).provenance_ == Provenance.from_dict(p)


def test_an_old_model_without_the_record_still_loads(fitted, data_csv, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(fitted[0], old)
    meta = json.loads((old / "hybrid.json").read_text())
    del meta["provenance"]
    (old / "hybrid.json").write_text(json.dumps(meta))
    m = HybridModel.load(old)
    assert m.provenance_ is None
    np.testing.assert_array_equal(m.theta_, HybridModel.load(fitted[0]).theta_)
    # Saved again, it gets a record (no data file known) and loads.
    again = HybridModel.load(m.save(tmp_path / "again"))
    assert again.provenance_ is not None and again.provenance_.inputs == ()


def test_a_model_fitted_in_the_library_records_its_data_file(data_csv, tmp_path):
    from dt_runtime.measurements.dataset import read_table

    m = HybridModel((), gp_inputs="none").fit(read_table(data_csv))
    p = json.loads((m.save(tmp_path / "lib") / "hybrid.json").read_text())["provenance"]
    assert [f["sha256"] for f in p["inputs"]] == [sha(data_csv)]
    # A loaded model saved again keeps its record's inputs, made anew by this software.
    p2 = json.loads((HybridModel.load(tmp_path / "lib").save(tmp_path / "lib2") / "hybrid.json").read_text())
    assert p2["provenance"]["inputs"] == p["inputs"]


def test_compare_and_diagnose_json_carry_the_record(fitted, data_csv, tmp_path):
    out, _ = fitted
    rc, res = run_json(["compare", "--data", str(data_csv), "--model", str(out), "--report", str(tmp_path)])
    assert rc == 0, res
    paths = {f["path"]: f["sha256"] for f in res["provenance"]["inputs"]}
    assert paths[str(data_csv.resolve())] == sha(data_csv)
    assert paths[str((out / "hybrid.json").resolve())] == sha(out / "hybrid.json")
    html = (tmp_path / "report.html").read_text()
    assert "Traceability" in html and sha(data_csv)[:12] in html
    rc, res = run_json(["diagnose", "--data", str(data_csv), "--gp-inputs", "none", "--candidates", "thermal",
                        "--folds", "3", "--instruments", str(EXAMPLE)])
    assert rc == 0, res
    p = res["provenance"]
    assert p["software"]["version"] == version() and sha(data_csv) in {f["sha256"] for f in p["inputs"]}
    assert p["instruments"][0]["role"] == "tracker"


# --------------------------------------------------------------------------- the demo

@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    from dt_runtime.workflows.demo import run_demo

    return run_demo(tmp_path_factory.mktemp("demo"), quick=True)


def test_the_demo_summary_records_its_configs_and_simulated_instruments(quick_demo):
    p = quick_demo.summary["provenance"]
    hashes = {f["path"]: f["sha256"] for f in p["inputs"]}
    for name in ("demo.yaml", "cell.yaml", "plan_quick.yaml", "scenarios/paper_default.yaml"):
        assert hashes[f"configs/{name}"] == sha(CONFIGS / name)
    tracker = next(i for i in p["instruments"] if i["role"] == "tracker")
    assert tracker["driver"] == "sim"
    assert tracker["uncertainty"]["terms"] == {"constant": {"value": 10e-6, "unit": "m"},
                                               "per_length": {"value": 0.02e-6, "unit": "m/m"}}
    assert {i["role"] for i in p["instruments"]} == {"robot", "tracker", "camera"}
    assert p["environment"]["temperature_c"]["n"] > 0
    assert p["software"]["version"] == version()


def test_the_demo_report_has_a_traceability_section(quick_demo):
    # Only the record: every other block becomes a note, the traceability block is drawn.
    html = build_demo_report(DemoResult({"provenance": quick_demo.summary["provenance"]}, {}))
    assert 'id="traceability"' in html and sha(CONFIGS / "cell.yaml")[:12] in html
    assert "10 um + 0.02 um/m" in html


# --------------------------------------------------------------------------- the instruments YAML

def bad(tmp_path, text: str) -> ConfigError:
    f = tmp_path / "inst.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_instruments(f)
    assert str(f) in str(err.value)
    return err.value


def test_the_example_instruments_yaml_validates():
    roles = [i.role for i in load_instruments(EXAMPLE)]
    assert roles == ["tracker", "camera", "thermometer"]


def test_the_instruments_yaml_fails_with_file_key_value_and_what_is_allowed(tmp_path):
    head = "instruments:\n  - role: tracker\n    kind: laser tracker\n"
    e = bad(tmp_path, head + "    uncertainty:\n      terms: {constant: {value: 15, unit: microns}}\n")
    assert e.key == "instruments.0.uncertainty.terms.constant.unit" and e.value == "microns"
    assert "'um'" in e.allowed
    e = bad(tmp_path, head + "    certifcate: X\n    uncertainty: {text: 10 um}\n")
    assert e.key == "instruments.0.certifcate" and "certificate" in e.allowed
    e = bad(tmp_path, head + "    uncertainty: {kind: expanded, text: U = 20 um}\n")
    assert "coverage factor 'k'" in e.allowed
    e = bad(tmp_path, head + "    uncertainty: {kind: standard}\n")
    assert "'text' and/or 'terms'" in e.allowed
    e = bad(tmp_path, head + "    calibration_date: '2026-02-30'\n    uncertainty: {text: 10 um}\n")
    assert e.key == "instruments.0.calibration_date" and e.value == "2026-02-30"
    e = bad(tmp_path, head + "    calibration_date: 2026-13-01\n    uncertainty: {text: 10 um}\n")
    assert "month must be in 1..12" in e.allowed
    e = bad(tmp_path, head + "    uncertainty: {text: 10 um}\n" + head[len("instruments:\n"):]
            + "    uncertainty: {text: 10 um}\n")
    assert "role 'tracker' given twice" in e.allowed
    bad(tmp_path, "instruments: []\n")
