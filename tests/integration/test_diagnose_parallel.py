"""The candidates of a diagnosis step cross-validated in worker processes (analysis.parallel) give
the same figures and the same verdict as in one process."""
from __future__ import annotations

import pytest

from dt_runtime.analysis.diagnose import DiagnoseOptions, diagnose
from dt_runtime.common.paths import CONFIGS
from dt_runtime.reports.verdicts import verdict
from tests.support import deploy_scenarios as sc


def test_two_workers_give_what_one_process_gives(monkeypatch):
    train, _ = sc.approach_backlash(seed=2, n_points=20, passes=3, speeds=(0.25,))
    options = DiagnoseOptions(robot=CONFIGS / "robots" / "ur10.yaml", auto=True,
                              candidates=("geometric", "backlash", "drift"))
    monkeypatch.setenv("DT_WORKERS", "1")
    one = diagnose(train, options)
    monkeypatch.setenv("DT_WORKERS", "2")
    two = diagnose(train, options)
    assert two.added == one.added and two.effects == one.effects
    assert [s.rmse_mm for s in two.steps] == pytest.approx([s.rmse_mm for s in one.steps], rel=1e-9)
    assert verdict(two) == verdict(one)


def test_a_bad_worker_count_is_refused(monkeypatch):
    from dt_kernel.errors import ConfigError
    from dt_runtime.analysis.parallel import workers

    monkeypatch.setenv("DT_WORKERS", "zero")
    with pytest.raises(ConfigError, match="DT_WORKERS"):
        workers()
