"""The data commands behind `dt fit` and `dt diagnose`: read a measurement table (or a
foreign file through an import mapping), train the hybrid error model, rank missing effects.

Rows are used in file order, which must be time order: the backlash and dynamic regressors
read the direction of approach from the previous row.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dt_runtime.metrology.stats import rms3
from dt_runtime.models import effects as fx
from dt_runtime.measurements.dataset import Dataset, read_meta_sidecar, read_table
from dt_runtime.analysis.diagnose import cross_validate, diagnose, folds_of, noise_floor
from dt_kernel.errors import DataError
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.common.paths import CONFIGS
from dt_runtime.common.progress import Progress

DEFAULT_ROBOT = CONFIGS / "robots" / "cobot_hc20_like.yaml"


@dataclass
class Data:
    dataset: Dataset
    info: dict  # source, rows, skipped rows, registration report (import), sidecar facts


def load_data(path: str | Path, mapping: str | Path | None = None, skip_bad: bool = False) -> Data:
    """The contract CSV, or a foreign file read through `mapping` (registered if needed)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such data file")
    info: dict = {"data": str(path)}
    if mapping is not None:
        from dt_runtime.measurements.importer import import_file

        ds, report = import_file(path, mapping, skip_bad=skip_bad)
        info["registration"] = report.to_dict()
    else:
        ds = read_table(path, skip_bad=skip_bad)
        side = read_meta_sidecar(path)
        if side:
            info["simulation"] = side
    info["n"] = ds.n
    info["skipped_rows"] = [str(s) for s in ds.skipped]
    return Data(ds, info)


def groups_of(ds: Dataset) -> np.ndarray:
    """Cross-validation groups: the target point; rows of unknown point get a group each
    only if their commanded positions differ (a model must not win by remembering a point)."""
    if ds.point_id is not None:
        return ds.point_id
    _, inv = np.unique(np.round(ds.commanded / 1e-6).astype(np.int64), axis=0, return_inverse=True)
    return inv.ravel()


def floor_of(d: Data) -> float | None:
    """The measurement noise floor (m): the simulator's, else the stated uncertainty's."""
    sim = d.info.get("simulation")
    if sim and sim.get("noise_floor_mm") is not None:
        return sim["noise_floor_mm"] * 1e-3
    return noise_floor(d.dataset.u)


def fit(d: Data, effects: tuple[str, ...], gp_inputs: str, robot: str | Path | None, out: str | Path,
        seed: int = 0, cv_folds: int = 0, gp_kw: dict | None = None,
        progress: Progress | None = None) -> dict:
    """Train and save the hybrid model; with cv_folds > 1 also its held-out RMS (grouped CV)."""
    progress = progress or Progress(enabled=False)
    ds = d.dataset
    t0 = time.perf_counter()
    model = HybridModel(effects, gp_inputs, seed=seed, robot=robot, gp_kw=gp_kw)
    progress.note(f"fitting effects [{', '.join(effects) or 'none'}] + GP on {gp_inputs} to {ds.n} rows")
    model.fit_dataset(ds)
    seconds = time.perf_counter() - t0
    model.save(out)
    res = {"out": str(out), "n": ds.n, "effects": list(effects), "gp_inputs": gp_inputs,
           "robot": model.robot, "fit_seconds": seconds,
           "train_rmse_mm": rms3(ds.error - model.predict_dataset(ds)) * 1e3,
           "parameters": model.parameters(), **{k: v for k, v in d.info.items() if k != "n"}}
    if cv_folds > 1:
        progress.note(f"held-out error: {cv_folds}-fold cross-validation grouped by target point")
        g = groups_of(ds)
        cv = cross_validate(tuple(effects), fx.Inputs.of(ds), ds.error, g, model.chain, gp_inputs,
                            folds_of(g, cv_folds, seed), seed, gp_kw,
                            thetas=model.gp_.thetas_ if model.gp_ is not None else None)
        res["heldout_rmse_mm"] = rms3(cv.residual) * 1e3
        res["as_is_rmse_mm"] = rms3(ds.error) * 1e3
    return res


def run_diagnose(d: Data, model_dir: str | Path | None = None, effects: tuple[str, ...] = (),
                 gp_inputs: str = "tcp_speed", robot: str | Path | None = None,
                 candidates: tuple[str, ...] | None = None, folds: int = 5, seed: int = 0,
                 gp_kw: dict | None = None, progress: Progress | None = None) -> dict:
    """Rank the effects the model lacks; the starting model is `model_dir`'s, or `effects` +
    GP on `gp_inputs`."""
    ds = d.dataset
    if model_dir is not None:
        m = HybridModel.load(model_dir)
        effects, gp_inputs, chain, gp_kw = m.effects, m.gp_inputs, m.chain, m.gp_kw
    else:
        chain = HybridModel((), "none", robot=robot).chain
    r = diagnose(fx.Inputs.of(ds), ds.error, groups_of(ds), chain, tuple(effects), gp_inputs,
                 candidates, folds, seed, noise_floor_m=floor_of(d), progress=progress, gp_kw=gp_kw)
    return r | {k: v for k, v in d.info.items() if k != "n"}
