"""`dt diagnose`: rank the physical effects the model lacks.

Cross-validation grouped by target point of the model with and without each candidate effect,
one-sided Wilcoxon test per held-out point; each significant candidate also held out the way
deployment brings new data (regions of the workspace, sessions, later times), side by side.

`--auto`: the whole compare/diagnose/add loop in one command (analysis.selection): each step adds
the change that explains most held-out variance if it is significant at alpha / (changes tested at
that step), explains at least --min-explained and also lowers the RMS on the deployment scheme;
candidates the campaign cannot separate from the pose are not tested; effects that read the same
factor are tested head to head; sessions that disagree are tested against the session terms. It
prints the steps (model, both held-out figures, p, explained fraction) and the verdict, whose last
sentence says whether to deploy. `--out MODEL` fits the final model on all rows and saves it (with
diagnose.json) for dt compare, dt calibrate --model and dt export, and residuals.csv beside it: every
row's held-out residual (by point) of the first and the final model (reports.residuals).
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import (
    add_data_args,
    add_effects_file_arg,
    add_mpe_arg,
    add_output_args,
    add_session_args,
    effects_catalogue,
    folds,
    input_files,
    load,
    names,
    progress,
)


def add_arguments(dg: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt diagnose`` (docs/cli.md, ``dt diagnose``).

    Parameters
    ----------
    dg : argparse.ArgumentParser
        The subcommand's parser.
    """
    add_data_args(dg)
    dg.add_argument("--model", default=None, metavar="MODEL", help="starting model (default: --effects + GP)")
    dg.add_argument("--effects", default="", metavar="a,b,...", help="starting model's effects without --model")
    dg.add_argument("--candidates", default="", metavar="a,b,...", help="effects to test (default all)")
    add_effects_file_arg(dg)
    dg.add_argument("--folds", type=folds, default=5, help="cross-validation folds (default 5)")
    dg.add_argument("--auto", action="store_true", help="the whole loop: add effects / switch GP inputs while "
                    "significant and better on new data (forward selection), then the verdict")
    dg.add_argument("--alpha", type=_fraction, default=0.01, help="--auto: family-wise level of each step (0.01)")
    dg.add_argument("--min-explained", type=_fraction, default=0.02,
                    help="--auto: smallest explained fraction of held-out variance worth adding (0.02)")
    dg.add_argument("--out", default=None, metavar="MODEL",
                    help="--auto: fit the final model on all rows and save it here (with diagnose.json and "
                         "residuals.csv, every row's held-out residual of the first and the final model); the "
                         "directory is replaced whole at the end")
    add_session_args(dg)
    dg.add_argument("--instruments", default=None, metavar="YAML",
                    help="the campaign's instruments and certificates (e.g. configs/instruments_example.yaml), "
                         "recorded in the provenance")
    add_mpe_arg(dg)
    add_output_args(dg)


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < v < 1:
        raise argparse.ArgumentTypeError(f"{v}: a fraction in (0, 1)")
    return v


def run(args: argparse.Namespace) -> Any:
    """Rank the candidate effects the model lacks by cross-validation.

    With ``--auto``, run the whole compare/diagnose/add loop instead.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    dict
        The result; with ``--json`` printed as one object (its keys: docs/cli.md).

    Raises
    ------
    TwinError
        For input the command refuses (``dt`` prints it and exits 2).
    """
    import contextlib
    import json
    from pathlib import Path

    from dt_kernel.errors import DataError
    from dt_runtime.analysis.diagnose import DiagnoseOptions, diagnose
    from dt_runtime.analysis.parallel import default_to_cores
    from dt_runtime.analysis.results import AutoResult
    from dt_runtime.cli.common import MODEL_MARKS, data_inputs, robot_of
    from dt_runtime.common.jsonsafe import jsonable
    from dt_runtime.common.outputs import staged
    from dt_runtime.reports.residuals import write_residuals
    from dt_runtime.reports.verdicts import with_verdict

    if args.out is not None and not args.auto:
        raise DataError("--out saves the final model of --auto; without --auto, fit a model with dt fit")
    default_to_cores()  # the candidates of a step in parallel, one process per core (DT_WORKERS)
    cat = effects_catalogue(args)  # passed down to the diagnosis and its worker processes
    d = load(args, cat)
    # --out: the final model and its verdict written whole or not at all (common.outputs)
    with (staged(args.out, "dt diagnose", marks=MODEL_MARKS, inputs=data_inputs(args)) if args.out is not None
          else contextlib.nullcontext()) as model_dir:
        options = DiagnoseOptions(
            model=args.model, effects=names(args.effects), gp_inputs=args.gp_inputs, robot=robot_of(args, d),
            candidates=names(args.candidates) or None, folds=args.folds, seed=args.seed,
            instruments=args.instruments, inputs=tuple(input_files(args)), auto=args.auto, alpha=args.alpha,
            min_explained=args.min_explained, out=model_dir, exclude_sessions=names(args.exclude_session),
            reference_session=args.reference_session, session_terms=names(args.session_term), catalogue=cat)
        r = diagnose(d, options, progress=progress(args))
        out = with_verdict(jsonable(r))
        if model_dir is not None:  # the verdict beside the model it chose, and its map of held-out residuals
            (Path(model_dir) / "diagnose.json").write_text(json.dumps(out, indent=2, allow_nan=False),
                                                           encoding="utf-8")
            assert isinstance(r, AutoResult) and r.heldout_rows is not None  # --out needs --auto (above)
            write_residuals(r.heldout_rows, model_dir)
    return out


def human(result: dict) -> str:
    """The text ``dt diagnose`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    from dt_runtime.reports.verdicts import floor_unknown

    if "steps" in result:  # --auto
        v = result["validation"]
        kind = v["deployment"]["kind"]
        lines = [f"from {result['start']} ({result['n']} rows): held out by point ({v['significance']['folds']} folds, "
                 f"the significance test) | on {kind} ({v['deployment']['folds']} folds, the decision)"]
        for s in result["steps"]:
            lines.append(f"  {s['model']:<44} {s['rmse_mm']:.4f} +/- {s['u_rmse_mm'] or 0:.4f} | "
                         f"{s['deploy_rmse_mm']:.4f} mm"
                         + (f"  -> {s['change']} (p = {s['p_value']:.2g}, explains "
                            f"{100 * s['explained_fraction']:.0f} %)" if s["change"] else ""))
        return "\n".join(lines + [result["verdict"]])
    lines = [f"held-out 3D RMS of the starting model: {result['rmse_base_mm']:.4f} mm"
             + (f" (noise floor {result['noise_floor_mm']:.4f} mm)" if result.get("noise_floor_mm") else "")]
    if not result.get("noise_floor_mm"):
        lines.append(floor_unknown(result) + ".")

    def fig(r: dict) -> str:
        dep = (f" | {r['deploy_kind']} {r['deploy_rmse_before_mm']:.4f} -> {r['deploy_rmse_after_mm']:.4f}"
               if r.get("deploy_kind") else "")
        return f"p = {r['p_value']:.2g}  RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm{dep}"

    lines += [f"  {r['effect']:<10} explains {100 * r['explained_fraction']:6.1f} %  {fig(r)}"
              for r in result["ranking"]]
    lines += [f"  GP on {r['gp_inputs']:<9} explains {100 * r['explained_fraction']:6.1f} %  {fig(r)}"
              for r in result.get("gp_inputs_ranking", [])]
    return "\n".join(lines + [result["verdict"]])
