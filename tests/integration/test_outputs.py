"""Outputs written whole or not at all (issue 22, item 4): a run into an existing directory
writes a temporary sibling and swaps it in at the end; an interrupted run (Ctrl-C, SIGTERM, an
exception) leaves the old output intact and says so (dt_runtime.common.outputs)."""
from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dt_kernel.errors import DataError
from dt_runtime.cli.main import main
from dt_runtime.common import outputs
from dt_runtime.common.outputs import final_path, staged
from dt_runtime.common.paths import CONFIGS, ROOT
from dt_runtime.common.provenance import shown_path
from dt_runtime.frames.kinematics import load_robot
from dt_runtime.measurements.dataset import Dataset, write_table


def _tree(d: Path) -> dict[str, str]:
    """Every file under d with its SHA-256: the state to compare before and after."""
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*"))
            if p.is_file()}


def _siblings(d: Path) -> list[str]:
    return sorted(p.name for p in d.parent.iterdir() if p.name.startswith(f".{d.name}."))


def _old(d: Path, mark: str) -> dict[str, str]:
    """A previous output: its mark file and a file the new run does not write."""
    d.mkdir(parents=True, exist_ok=True)
    (d / mark).write_text("old run\n")
    (d / "old_only.txt").write_text("from the previous run\n")
    return _tree(d)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# --------------------------------------------------------------------------- the helper

def test_a_finished_run_replaces_the_directory_whole(tmp_path):
    out = tmp_path / "m"
    _old(out, "hybrid.json")
    with staged(out, "dt fit", marks=("hybrid.json",)) as work:
        assert work.parent == tmp_path and work.name.startswith(".m.partial-") and not any(work.iterdir())
        (work / "hybrid.json").write_text("new run\n")
        assert (out / "hybrid.json").read_text() == "old run\n"  # the old output stays until the end
        assert final_path(work / "hybrid.json") == out / "hybrid.json"
    assert _tree(out).keys() == {"hybrid.json"} and (out / "hybrid.json").read_text() == "new run\n"
    assert _siblings(out) == [] and final_path(work) == work  # nothing staged any more


@pytest.mark.parametrize("error", [KeyboardInterrupt, DataError])
def test_an_interrupted_or_failed_run_leaves_the_old_output_intact_and_says_so(tmp_path, capsys, error):
    out = tmp_path / "m"
    before = _old(out, "hybrid.json")
    with pytest.raises(error):
        with staged(out, "dt fit", marks=("hybrid.json",)) as work:
            (work / "hybrid.json").write_text("new run\n")
            raise error("stop")
    assert _tree(out) == before and _siblings(out) == []
    why = "interrupted" if error is KeyboardInterrupt else "failed"
    assert f"dt fit: {why}: {out} left as it was (the new output was not kept)" in capsys.readouterr().err


def test_an_interrupted_first_run_writes_nothing(tmp_path, capsys):
    with pytest.raises(KeyboardInterrupt):
        with staged(tmp_path / "new", "dt demo") as work:
            (work / "summary.json").write_text("{}")
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == [] and f"{tmp_path / 'new'} not written" in capsys.readouterr().err


@pytest.mark.parametrize("case, message", [
    ("foreign", "exists and is not a previous output of dt fit (it has none of hybrid.json)"),
    ("file", "a file, not a directory"),
    ("input", "holds the input"),
    ("cwd", "holds the working directory"),
])
def test_a_directory_that_is_not_a_previous_output_is_refused_before_anything_is_written(tmp_path, monkeypatch,
                                                                                        case, message):
    out = tmp_path / "m"
    data = out / "data.csv"
    if case == "file":
        out.write_text("x")
    else:
        out.mkdir()
        data.write_text("x,y,z\n")
    if case == "cwd":
        (out / "hybrid.json").write_text("old")
        monkeypatch.chdir(out)
    if case == "input":
        (out / "hybrid.json").write_text("old")
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(DataError, match=re.escape(message)) as e:
        with staged(out, "dt fit", marks=("hybrid.json",), inputs=[data] if case == "input" else []):
            pytest.fail("nothing may be staged")
    assert str(out) in str(e.value) and sorted(p.name for p in tmp_path.iterdir()) == before


def test_what_a_killed_run_left_is_cleaned_up_or_put_back(tmp_path, capsys):
    dead = _dead_pid()
    out = tmp_path / "twin"
    partial = tmp_path / f".twin.partial-{dead}"
    previous = tmp_path / f".twin.previous-{dead}"
    partial.mkdir()
    (partial / "twin.json").write_text("half written")
    previous.mkdir()  # killed between the two renames: the old output moved aside, the new not yet in place
    (previous / "twin.json").write_text("old run")
    with staged(out, "dt calibrate", marks=("twin.json",)) as work:
        assert (out / "twin.json").read_text() == "old run"  # put back before anything else
        (work / "twin.json").write_text("new run")
    assert (out / "twin.json").read_text() == "new run" and _siblings(out) == []
    assert f"put back the previous output that a killed run (pid {dead}) had moved aside" in capsys.readouterr().err


def test_a_signal_during_the_swap_is_delivered_after_it(tmp_path):
    out = tmp_path / "m"
    _old(out, "hybrid.json")
    real = outputs._swap_in

    def swap_with_ctrl_c(work: Path, target: Path) -> None:
        with outputs._Held():
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C between the renames
            target.rename(tmp_path / "aside")
            work.rename(target)
        pytest.fail("the held Ctrl-C must arrive when the swap is done")

    outputs._swap_in = swap_with_ctrl_c  # type: ignore[assignment]
    ctrl_c = signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C is KeyboardInterrupt, as in dt
    try:
        with pytest.raises(KeyboardInterrupt):
            with staged(out, "dt fit", marks=("hybrid.json",)) as work:
                (work / "hybrid.json").write_text("new run\n")
    finally:
        outputs._swap_in = real  # type: ignore[assignment]
        signal.signal(signal.SIGINT, ctrl_c)
    assert (out / "hybrid.json").read_text() == "new run\n"  # swapped whole, then interrupted


def test_the_record_names_a_staged_file_where_it_will_be(tmp_path):
    out = tmp_path / "demo"
    with staged(out, "dt demo") as work:
        (work / "campaign").mkdir()
        f = work / "campaign" / "doe.csv"
        f.write_text("x")
        assert shown_path(f) == str((out / "campaign" / "doe.csv").resolve())  # the provenance's name of it
        assert shown_path(tmp_path) == str(tmp_path.resolve())


# --------------------------------------------------------------------------- every command uses it

def _table(path: Path) -> Path:
    cobot = load_robot(CONFIGS / "robots" / "cobot_hc20_like.yaml")
    rng = np.random.default_rng(0)
    q = rng.uniform(-0.8, 0.8, (40, 6)) + np.array([0.0, -0.3, 0.9, 0.0, 0.7, 0.0])
    return write_table(Dataset(commanded=cobot.fk(q), error=rng.normal(0, 2e-4, (40, 3)), joints=q,
                               speed=np.full(40, 0.25), point_id=np.arange(40)), path)


def _interrupt(*_a, out=None, **_k):
    """A command's long step: writes into the staged directory, then Ctrl-C."""
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "hybrid.json").write_text("new run, half written")
    raise KeyboardInterrupt


@pytest.mark.parametrize("command", ["demo", "calibrate", "campaign", "fit", "diagnose", "compare"])
def test_every_command_that_writes_a_directory_leaves_the_old_one_when_interrupted(tmp_path, monkeypatch, capsys,
                                                                                  command):
    data = _table(tmp_path / "d.csv")
    out = tmp_path / "out"
    mark = {"demo": "summary.json", "calibrate": "twin.json", "campaign": "model", "fit": "hybrid.json",
            "diagnose": "hybrid.json", "compare": "compare.json"}[command]
    before = _old(out, mark)
    if command == "demo":
        monkeypatch.setattr("dt_runtime.workflows.demo.run_demo", lambda out, **k: _interrupt(out=out))
        argv = ["demo", "--quick", "--out", str(out)]
    elif command == "calibrate":
        monkeypatch.setattr("dt_runtime.workflows.campaign_dir.calibrate_campaign",
                            lambda f, o, out, *a: _interrupt(out=out))
        argv = ["calibrate", "--registration", str(data), "--doe", str(data), "--out", str(out)]
    elif command == "campaign":
        monkeypatch.setattr("dt_runtime.cli.campaign._measure_and_calibrate", lambda *a: _interrupt(out=a[7]))
        argv = ["campaign", "--config", str(CONFIGS / "runtime.yaml"), "--out", str(out)]
    elif command == "fit":
        monkeypatch.setattr("dt_runtime.analysis.training.fit", lambda *a, **k: _interrupt(out=a[4]))
        argv = ["fit", "--data", str(data), "--out", str(out)]
    elif command == "diagnose":
        monkeypatch.setattr("dt_runtime.analysis.diagnose.diagnose", lambda data, options, **k: _interrupt(out=options.out))
        argv = ["diagnose", "--data", str(data), "--auto", "--out", str(out)]
    else:
        monkeypatch.setattr("dt_runtime.analysis.compare.compare", lambda *a, **k: ({}, {}))
        monkeypatch.setattr("dt_runtime.reports.compare_report.write_compare_report", lambda r, a, o: _interrupt(out=o))
        argv = ["compare", "--data", str(data), "--model", str(tmp_path / "m"), "--report", str(out)]
    assert main(argv) == 130
    err = capsys.readouterr().err
    assert _tree(out) == before and _siblings(out) == [], err
    assert f"dt {command}: interrupted: {out} left as it was (the new output was not kept)" in err


def _child(tmp_path: Path, out: Path, sig: signal.Signals) -> subprocess.CompletedProcess:
    """`dt fit` in a real process that sends itself `sig` right after the model is saved (a
    deterministic point: the new model is complete in the staged directory, not yet in place)."""
    code = f"""
import os, signal, sys, time
from dt_runtime.models.hybrid import HybridModel
save = HybridModel.save
def save_then_signal(self, *a, **k):
    path = save(self, *a, **k)
    os.kill(os.getpid(), signal.{sig.name})
    time.sleep(30)  # the signal arrives during this
    return path
HybridModel.save = save_then_signal
from dt_runtime.cli.main import main
sys.exit(main(["fit", "--data", {str(tmp_path / 'd.csv')!r}, "--effects", "geometric", "--gp-inputs", "none",
               "--out", {str(out)!r}, "--no-progress"]))
"""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.mark.parametrize("sig, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_real_process_interrupted_by_a_signal_leaves_the_old_model(tmp_path, sig, status):
    _table(tmp_path / "d.csv")
    out = tmp_path / "model"
    assert main(["fit", "--data", str(tmp_path / "d.csv"), "--effects", "geometric", "--gp-inputs", "none",
                 "--out", str(out), "--json", "--no-progress"]) == 0
    before = _tree(out)
    assert "hybrid.json" in before
    p = _child(tmp_path, out, sig)
    assert p.returncode == status, p.stderr[-2000:]
    assert f"dt fit: interrupted: {out} left as it was (the new output was not kept)" in p.stderr
    assert _tree(out) == before and _siblings(out) == []
    assert "Traceback" not in p.stderr


def test_a_staged_demo_records_where_its_files_are(quick_demo):
    rc, stdout, out = quick_demo
    assert rc == 0 and _siblings(out) == []
    summary = json.loads((out / "summary.json").read_text())
    assert summary["campaign"] == str(out / "campaign" / "campaign.yaml")
    for f in out.rglob("*"):  # no file names the temporary directory it was written in
        if f.is_file() and f.suffix in (".json", ".html", ".yaml", ".csv"):
            assert ".partial-" not in f.read_text(encoding="utf-8", errors="replace"), f
