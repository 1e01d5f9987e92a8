"""The bounded-correction rules over a whole path (twin.bounds.check_path_bounds): what
`dt run` refuses at start for a streamed path, set-point by set-point as `Corrector` would."""
from __future__ import annotations

import numpy as np

from dt_runtime.twin.bounds import Limits, check_path_bounds


def line(n: int = 50) -> np.ndarray:
    return np.column_stack([np.linspace(0.8, 1.0, n), np.zeros(n), np.full(n, 0.5)])


def test_a_smooth_small_correction_passes():
    targets = line()
    commands = targets + np.array([1e-4, -2e-4, 5e-5]) + 1e-6 * np.arange(50)[:, None]
    assert check_path_bounds(Limits(), targets, commands) == ""


def test_each_rule_names_the_first_set_point_that_breaks_it():
    lim, targets = Limits(), line()
    big = targets.copy()
    big[7] += [3e-3, 0, 0]  # 3 mm: above max_correction_m 2 mm
    assert check_path_bounds(lim, targets, big).startswith("set-point 8: correction 3.000 mm exceeds")
    jump = targets.copy()
    jump[20:] += [1.5e-3, 0, 0]  # a 1.5 mm step over 4 mm of travel: above 0.2 mm + 0.01 x 4 mm
    assert check_path_bounds(lim, targets, jump).startswith("set-point 21: correction changes by 1.500 mm")
    out = targets.copy()
    out[3] = [1.7, 0.0, 0.5]  # beyond workspace_max_m x 1.6 m
    assert "set-point 4: target" in check_path_bounds(Limits(max_correction_m=0.05, max_correction_step_m=0.05,
                                                              max_correction_gradient=1.0), targets, out)
    nan = targets.copy()
    nan[0, 1] = np.nan
    assert check_path_bounds(lim, targets, nan) == "set-point 1: no finite correction"
