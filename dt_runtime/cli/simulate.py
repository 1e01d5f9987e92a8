"""`dt simulate`: measurement data from the simulated cell for a scenario.

Run a scenario's experiment plan on the simulated cell (tracker registered by the three-line
method) and write the measurement table (docs/measurement-table.md) as CSV, with
FILE.csv.meta.json: scenario, seed, registration residual, noise floor.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import add_output_args, progress, seed_number


def add_arguments(sm: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt simulate`` (docs/cli.md, ``dt simulate``).

    Parameters
    ----------
    sm : argparse.ArgumentParser
        The subcommand's parser.
    """
    sm.add_argument("--scenario", required=True, metavar="FILE",
                    help="scenario YAML (configs/scenarios/), optional 'data:' block: plan, phases, doe_reps, cell")
    sm.add_argument("--out", required=True, metavar="FILE.csv", help="output CSV")
    sm.add_argument("--seed", type=seed_number, default=None, help="overrides the scenario's and the plan's seed")
    add_output_args(sm)


def run(args: argparse.Namespace) -> Any:
    """Run a scenario's plan on the simulated cell and write the measurement table.

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
    from dt_runtime.workflows.simulate import simulate

    return simulate(args.scenario, args.out, seed=args.seed, progress=progress(args))


def human(result: dict) -> str:
    """The text ``dt simulate`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    dropped = f" ({result['dropped_rows']} rows dropped)" if result.get("dropped_rows") else ""
    return (f"wrote {result['n']} rows of {result['name']} ({', '.join(result['phases'])}; seed {result['seed']}) to "
            f"{result['out']}{dropped}\nregistration RMS {result['registration_rms_mm']:.4f} mm, noise floor "
            f"{result['noise_floor_mm']:.4f} mm (its meta: {result['out']}.meta.json; --json for the whole summary)")
