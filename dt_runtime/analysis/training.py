"""`dt fit` on loaded data: train the hybrid error model, save it, and (with CV) state its
held-out RMS."""
from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from dt_kernel.units import MM_PER_M
from dt_runtime.analysis.crossval import cross_validate, folds_of, groups_of
from dt_runtime.analysis.data import Data, select_sessions
from dt_runtime.analysis.results import FitResult
from dt_runtime.common.outputs import final_path
from dt_runtime.common.progress import Progress
from dt_runtime.common.provenance import Provenance, build, files_under, load_instruments
from dt_runtime.frames import robots
from dt_runtime.measurements.checks import check_dataset
from dt_runtime.measurements.dataset import Dataset, meta_path
from dt_runtime.metrology.stats import rms3
from dt_runtime.models import effects as fx
from dt_runtime.models.gp import GPOptions
from dt_runtime.models.hybrid import HybridModel, resolve_chain


def fit(d: Data, effects: tuple[str, ...], gp_inputs: str, robot: str | Path | None, out: str | Path,
        seed: int = 0, cv_folds: int = 0, gp_options: GPOptions | None = None,
        progress: Progress | None = None, instruments: str | Path | None = None,
        inputs: Sequence[str | Path] = (), session_terms: tuple[str, ...] = (),
        exclude_sessions: Sequence[str | int] = (), reference_session: str | int | None = None,
        catalogue: fx.Catalogue | None = None) -> FitResult:
    """Train and save the hybrid model; with cv_folds > 1 also its held-out RMS (grouped CV).
    The model and the result carry the traceability record (`provenance`): the data file, its
    simulation sidecar and `inputs` (e.g. the import mapping) hashed, the robot config, the
    instruments of the `instruments` YAML and the temperature range of the data. Several sessions:
    `session_terms` fitted as nuisance (never deployed; against `reference_session`), and
    `exclude_sessions` left out. `catalogue`: the effects the names refer to (e.g. with
    --effects-file's declarations, which the saved model keeps); default `effects.default()`.

    Parameters
    ----------
    d : Data
        The data.
    effects : tuple of str
        The effects.
    gp_inputs : str
        The GP's inputs.
    robot : str or Path or None
        The robot reference.
    out : str or Path
        The model directory.
    seed : int, optional
        Seed of the GP's starts and the folds.
    cv_folds : int, optional
        > 1: also the held-out RMS.
    gp_options : GPOptions, optional
        The GP's options.
    progress : Progress, optional
        Where progress is reported.
    instruments : str or Path, optional
        The instruments YAML.
    inputs : sequence of str or Path, optional
        Other input files to record.
    session_terms : tuple of str, optional
        Session terms fitted as nuisance.
    exclude_sessions : sequence, optional
        Sessions left out.
    reference_session : str or int, optional
        The reference session.
    catalogue : Catalogue, optional
        The call's effects.

    Returns
    -------
    FitResult
    """
    progress = progress or Progress(enabled=False)
    cat = catalogue if catalogue is not None else fx.default()
    cat.check_names(effects)
    d, _, ref = select_sessions(d, exclude_sessions, reference_session)
    ds = d.dataset
    # The joints are checked against the robot config when the model reads them.
    chain = resolve_chain(robot) if any(cat.get(e).needs_chain or cat.get(e).uses_chain for e in effects) else None
    reads_joints = gp_inputs == "joints" or any("joints" in cat.get(e).reads(chain) for e in effects)
    d.info.update(check_dataset(ds, resolve_chain(robot) if reads_joints and ds.joints is not None else None,
                                d.info.get("data")))
    prov = data_provenance(ds, d.info.get("data"), robot, instruments, inputs)
    t0 = time.perf_counter()
    model = HybridModel(tuple(effects), gp_inputs, seed=seed, robot=robot, gp_options=gp_options,
                        nuisance=tuple(session_terms), reference_session=ref, catalogue=cat)
    progress.note(f"fitting effects [{', '.join(effects) or 'none'}] + GP on {gp_inputs} to {ds.n} rows")
    model.fit(ds)
    seconds = time.perf_counter() - t0
    model.save(out, provenance=prov)
    res = FitResult(str(final_path(out)), ds.n, list(effects), gp_inputs, model.robot_, seconds,
                    rms3(ds.error - model.predict(ds)) * MM_PER_M, model.parameters(),
                    {k: v for k, v in d.info.items() if k != "n"}, provenance=prov,
                    base_parameters=model.base_parameters())
    if cv_folds > 1:
        progress.note(f"held-out error: {cv_folds}-fold cross-validation grouped by target point")
        g = groups_of(ds)
        # The model's configuration with its GP hyperparameters: the folds refit the rest.
        cv = cross_validate(model, ds, ds.error, g, folds_of(g, cv_folds, seed),
                            thetas=model.gp_.thetas_ if model.gp_ is not None else None)
        res.heldout_rmse_mm = rms3(cv.residual) * MM_PER_M
        res.as_is_rmse_mm = rms3(ds.error) * MM_PER_M
    return res


def data_provenance(ds: Dataset, data_file: str | Path | Sequence[str | Path] | None = None, robot: object = None,
                    instruments: str | Path | None = None, inputs: Sequence[str | Path] = (),
                    models: Sequence[object] = ()) -> Provenance:
    """The traceability record of a command on measured data: the data file (default the
    dataset's source) and its simulation sidecar, `inputs` (e.g. an import mapping), the files of
    the saved `models` (directories; fitted objects have none) and the `instruments` YAML, hashed;
    the robot config (a path) or its name (a Chain); the instruments; the data's temperature.

    Parameters
    ----------
    ds : Dataset
        The data.
    data_file : str, Path or sequence, optional
        The data file(s).
    robot : object, optional
        A robot config path or a Chain.
    instruments : str or Path, optional
        The instruments YAML.
    inputs : sequence of str or Path, optional
        Other input files.
    models : sequence, optional
        Model directories or fitted models.

    Returns
    -------
    Provenance
    """
    srcs: list[str | Path] = ([Path(f) for f in data_file] if isinstance(data_file, (list, tuple))
                              else [Path(data_file) if isinstance(data_file, (str, Path)) else ds.source])
    files: list[str | Path] = [f for src in srcs if src and Path(src).is_file() for f in (src, meta_path(src))]
    for m in models:
        files += files_under(m) if isinstance(m, (str, Path)) and Path(m).is_dir() else []
    files += [*inputs, *([instruments] if instruments is not None else [])]
    robot_file, robot_text = robots.record(robot) if isinstance(robot, (str, Path)) else (None, None)
    return build(files, robot=robot_file, robot_name=getattr(robot, "name", robot_text),
                 instruments=load_instruments(instruments) if instruments is not None else (),
                 temperature=ds.temperature)
