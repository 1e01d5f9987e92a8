"""The noise floor from the data's own replicates (analysis.replicates): revisits of a pose under the
same conditions give the tracker's noise on the UR10 generator's repeatability campaigns, whatever
effect is hidden, and `dt diagnose --auto` stops on it; a file without replicates says what to measure."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from dt_runtime.analysis.data import replicate_floor
from dt_runtime.analysis.replicates import REVISIT, TO_MEASURE, VISIT, conditions, pooled_floor, revisit_groups
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.dataset import Dataset, write_table
from tests.support.ur10_generator import generate, noise_floor_mm

UR10 = CONFIGS / "robots" / "ur10.yaml"
CAMPAIGN = {"n_points": 10, "passes": 24, "dt_s": 30.0, "order": "cycle"}  # ~40 min, every point from 2 sides


def _revisits(effect: str, seed: int = 1) -> Dataset:
    """A repeatability campaign with the hidden `effect`, the stated uncertainty dropped."""
    return dataclasses.replace(generate(effect, seed, **CAMPAIGN), u=None)


@pytest.mark.parametrize("effect", ["none", "backlash", "thermal", "drift"])
def test_revisits_give_the_trackers_noise_whatever_effect_is_hidden(effect):
    f = replicate_floor(_revisits(effect))
    assert f is not None and f.definition == REVISIT and f.dof >= 50
    assert f.value_m * 1e3 == pytest.approx(noise_floor_mm(), rel=0.15), (effect, f)


def test_pooling_revisits_from_either_side_would_take_the_backlash_for_noise():
    ds = _revisits("backlash")
    without = tuple(c for c in conditions() if c != "direction")
    blind = pooled_floor(ds.error, revisit_groups(ds, without))
    assert blind is not None and blind[0] * 1e3 > 2 * noise_floor_mm()


def _two_poses(n: int = 40, **columns) -> Dataset:
    """Two poses visited alternately, one row every 10 s, the same approach each time."""
    q = np.where((np.arange(n) % 2 == 0)[:, None], [0.1, -1.0, -1.0, -1.0, 1.0, 0.0],
                 [0.3, -1.2, -0.8, -1.2, 1.2, 0.2])
    p = np.where((np.arange(n) % 2 == 0)[:, None], [0.5, 0.1, 0.4], [0.6, -0.1, 0.3])
    base = {"t": 10.0 * np.arange(n), "speed": np.full(n, 0.25), "payload": np.full(n, 5.0),
            "temperature": np.full(n, 21.0)}
    return Dataset(commanded=p, error=np.zeros((n, 3)), joints=q, **(base | columns))


@pytest.mark.parametrize("column, values", [
    ("speed", lambda n: np.where(np.arange(n) % 4 < 2, 0.25, 0.5)),
    ("payload", lambda n: np.where(np.arange(n) % 4 < 2, 5.0, 0.0)),
    ("temperature", lambda n: 21.0 + 0.3 * (np.arange(n) % 4 >= 2) * np.arange(n) / 4),
    ("t", lambda n: 700.0 * np.arange(n)),
])
def test_a_revisit_that_differs_in_what_an_effect_reads_is_not_pooled(column, values):
    ds = _two_poses(**{column: values(40)})
    g = revisit_groups(ds)
    col = np.asarray(getattr(ds, column))
    labels, counts = np.unique(g[g >= 0], return_counts=True)
    pooled = labels[counts > 1]
    assert len(pooled) == 0 if column == "t" else len(pooled) >= 4  # 700 s apart: no revisit is close enough
    for label in pooled:
        spread = np.ptp(col[g == label])
        assert spread <= {"speed": 0.0, "payload": 0.0, "temperature": 0.5, "t": 600.0}[column], (column, label)


def test_revisits_alike_in_everything_are_one_group_per_pose():
    g = revisit_groups(_two_poses())
    assert g[0] == -1  # its approach is not in the data
    assert len(np.unique(g[1:])) == 2 and np.all(g[1:] >= 0)


def test_consecutive_readings_come_first():
    ds = _revisits("none")
    twice = ds.select(np.repeat(np.arange(ds.n), 2))  # every visit read twice in a row
    f = replicate_floor(twice)
    assert f is not None and f.definition == VISIT and f.dof == ds.n


def _diagnose(ds: Dataset, path, capsys) -> dict:
    csv = write_table(ds, path)
    assert main(["diagnose", "--data", str(csv), "--robot", str(UR10), "--auto", "--json", "--no-progress"]) == 0
    return json.loads(capsys.readouterr().out)


def test_diagnose_auto_stops_on_the_floor_of_the_revisits(tmp_path, capsys):
    out = _diagnose(_revisits("drift"), tmp_path / "revisits.csv", capsys)
    assert out["noise_floor_mm"] == pytest.approx(noise_floor_mm(), rel=0.15)
    assert out["floor_ratio"] == pytest.approx(out["final_rmse_mm"] / out["noise_floor_mm"])
    src = out["noise_floor"]["source"]
    assert src.startswith("the scatter of replicates: " + REVISIT) and "dof in" in src
    assert "drift" in out["effects"] and src in out["verdict"]


def test_without_replicates_the_floor_is_not_known_and_the_output_says_what_to_measure(tmp_path, capsys):
    ds = dataclasses.replace(generate("none", 1), u=None)  # every pass in a new order: no revisit alike
    out = _diagnose(ds, tmp_path / "random.csv", capsys)
    assert out["noise_floor_mm"] is None and out["floor_ratio"] is None
    assert out["noise_floor"]["to_measure"] == TO_MEASURE
    assert "The noise floor is not known" in out["verdict"] and TO_MEASURE in out["verdict"]
    assert main(["diagnose", "--data", str(tmp_path / "random.csv"), "--robot", str(UR10), "--no-progress"]) == 0
    text = capsys.readouterr().out  # the one-step diagnosis, as a user reads it
    assert "The noise floor is not known" in text and TO_MEASURE in text
