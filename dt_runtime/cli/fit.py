"""`dt fit`: train an error model (physical effect terms + GP) and save it.

error = sum of physical effect terms + GP on what is left. Effects: geometric, compliance, gear,
backlash, thermal, dynamic, drift.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import (
    add_data_args,
    add_effects_file_arg,
    add_output_args,
    add_session_args,
    cv_folds,
    effects_catalogue,
    input_files,
    load,
    names,
    parameter_lines,
    progress,
)


def add_arguments(ft: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt fit`` (docs/cli.md, ``dt fit``).

    Parameters
    ----------
    ft : argparse.ArgumentParser
        The subcommand's parser.
    """
    add_data_args(ft)
    ft.add_argument("--effects", default="", metavar="a,b,...", help="effect terms (default none: the paper's GP)")
    add_effects_file_arg(ft)
    ft.add_argument("--out", required=True, metavar="MODEL",
                    help="model directory (JSON + NPZ), replaced whole once the model is saved")
    ft.add_argument("--cv", type=cv_folds, default=0, metavar="K",
                    help="also report the held-out RMS by K-fold CV grouped by target point")
    add_session_args(ft)
    ft.add_argument("--instruments", default=None, metavar="YAML",
                    help="the campaign's instruments and certificates (e.g. configs/instruments_example.yaml), "
                         "recorded in the provenance")
    add_output_args(ft)


def run(args: argparse.Namespace) -> Any:
    """Train an error model (the named effect terms and a GP) on the data and save it.

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
    from dt_runtime.analysis.training import fit
    from dt_runtime.cli.common import MODEL_MARKS, data_inputs, robot_of
    from dt_runtime.common.outputs import staged

    cat = effects_catalogue(args)
    d = load(args, cat)
    with staged(args.out, "dt fit", marks=MODEL_MARKS, inputs=data_inputs(args)) as out:  # whole or not at all
        return fit(d, names(args.effects), args.gp_inputs, robot_of(args, d), out,
                   seed=args.seed, cv_folds=args.cv, progress=progress(args), instruments=args.instruments,
                   inputs=input_files(args), session_terms=names(args.session_term),
                   exclude_sessions=names(args.exclude_session), reference_session=args.reference_session,
                   catalogue=cat)


def human(result: dict) -> str:
    """The text ``dt fit`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    out = [f"model saved to {result['out']} ({result['n']} rows, {result['fit_seconds']:.1f} s); "
           f"training 3D RMS {result['train_rmse_mm']:.4f} mm"]
    if "heldout_rmse_mm" in result:
        out.append(f"held-out 3D RMS {result['heldout_rmse_mm']:.4f} mm (as is {result['as_is_rmse_mm']:.4f} mm)")
    return "\n".join(out + parameter_lines(result["parameters"], result.get("base_parameters")))
