"""`dt demo --quick` end to end through the CLI: one JSON object, the paper's figures met."""
import json
import shutil

import pytest

from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS

KEYS = {"precision_before_mm", "precision_after_mm", "improvement_pct", "true_rms_uncorrected_mm",
        "true_rms_corrected_mm", "true_error_reduction_pct", "coverage_95"}


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    import io
    import contextlib

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["demo", "--quick", "--json", "--no-progress", "--out", str(out)])
    return rc, buf.getvalue(), out


def test_prints_exactly_one_json_object_with_the_contract_keys(quick):
    rc, stdout, out = quick
    assert rc == 0
    summary = json.loads(stdout)  # the whole of stdout is one object
    assert KEYS <= summary.keys()
    assert set(summary["coverage_95"]) == {"x", "y", "z"}
    assert json.loads((out / "summary.json").read_text()) == summary
    assert (out / "report.html").stat().st_size > 10_000
    assert (out / "model" / "twin.json").exists()


def test_quick_demo_meets_the_papers_figures(quick):
    s = json.loads(quick[1])
    assert s["improvement_pct"] >= 77.8
    assert s["true_error_reduction_pct"] >= 75.0
    # 28 validation points: one miss is 3.6 %, so the quick run can only show 96.4 % or 100 %;
    # the 90-99 % figure is measured by the full demo (README).
    assert all(0.9 <= c <= 1.0 for c in s["coverage_95"].values())
    t3 = s["table3_as_is"]["e_lt_doe"]
    assert t3["x"]["std_mm"] > t3["y"]["std_mm"] > 0.15  # Table 3 scale, x largest


def test_unreachable_plan_targets_are_reported_before_anything_moves(tmp_path, capsys):
    for name in ("demo.yaml", "cell.yaml", "plan_quick.yaml", "plan_paper.yaml"):
        shutil.copy(CONFIGS / name, tmp_path / name)
    (tmp_path / "scenarios").mkdir()
    shutil.copy(CONFIGS / "scenarios" / "paper_default.yaml", tmp_path / "scenarios")
    (tmp_path / "plan_quick.yaml").write_text(
        (CONFIGS / "plan_quick.yaml").read_text() + "center_m: [1.9, 0.0, 0.55]\n")
    rc = main(["demo", "--quick", "--json", "--no-progress", "--config", str(tmp_path / "demo.yaml"),
               "--out", str(tmp_path / "out")])
    out = capsys.readouterr()
    assert rc == 2
    err = json.loads(out.out)["error"]
    assert "unreachable" in err and "target #" in err
    assert not (tmp_path / "out" / "summary.json").exists()
