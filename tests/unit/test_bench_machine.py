"""The machine a timing figure was taken on (`benchmarks._common`): the reference workload's
timings, the load and CPU around a benchmark, figures relative to the workload, and the busy core
of a run under load (no timing is asserted: only what is reported and how it is derived)."""
import os

import pytest

from benchmarks._common import REFERENCE_NOMINAL_S, Machine, busy_core, reference_workload


def test_the_reference_workload_reports_its_parts():
    r = reference_workload()
    assert set(r) == {"seconds", "cpu_seconds", "python_s", "numpy_s"}
    assert r["seconds"] > 0 and r["cpu_seconds"] > 0
    assert r["python_s"] + r["numpy_s"] == pytest.approx(r["seconds"], abs=2e-4)  # rounded to 0.1 ms


def test_a_run_reports_the_machine_and_its_figures_relative_to_the_workload():
    with Machine() as m:
        sum(range(10_000))
    rep = m.report()
    assert rep["reference_s"] == min(rep["reference"]["before"]["seconds"], rep["reference"]["after"]["seconds"])
    assert rep["speed"] == pytest.approx(REFERENCE_NOMINAL_S / rep["reference_s"], rel=1e-3)
    assert set(rep["load"]) == {"start", "end"} and rep["cores"] == os.cpu_count()
    rel = m.relative(times_s={"tick_s": 2 * m.ref_s, "none": None}, rates_hz={"rate_hz": 10.0 / m.ref_s})
    assert rel == {"tick_s_per_ref": pytest.approx(2.0, rel=1e-5), "none_per_ref": None,
                   "rate_hz_x_ref": pytest.approx(10.0, abs=0.01)}


def test_a_busy_core_runs_only_inside():
    with busy_core(False) as on:
        assert on is False
    before = _children()  # the suite's own (an emulator a session fixture started) are not the spinner
    with busy_core(True, max_s=30.0) as on:
        assert on is True
        kids = _children() - before
        assert kids
    assert not (_children() & kids)


def _children() -> set[str]:
    return {p for p in os.listdir("/proc") if p.isdigit() and _parent(p) == os.getpid()}


def _parent(pid: str) -> int:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return -1
