"""`dt export`: the calibrated robot (the fitted geometric effect applied to the nominal
kinematics) as a URDF or a DH robot config, loaded back and checked against the calibration.

Apply the identifiable combinations of a fitted geometric effect to the nominal kinematics and
write them as a URDF (joint origins adjusted) or a standard DH table in the robot config format
(configs/robots/*.yaml); the file is loaded back and its TCP compared with the calibrated one at
the training joint configurations. Parameters the data cannot identify are listed, not exported.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import add_output_args


def add_arguments(ex: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt export`` (docs/cli.md, ``dt export``).

    Parameters
    ----------
    ex : argparse.ArgumentParser
        The subcommand's parser.
    """
    src = ex.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", metavar="MODEL", help="a model directory of dt fit with --effects geometric")
    src.add_argument("--twin", metavar="TWIN", help="a twin directory whose maps hold a geometric effect")
    ex.add_argument("--format", required=True, metavar="urdf|dh", help="urdf or dh (robot config YAML)")
    ex.add_argument("--out", required=True, metavar="FILE", help="the file to write (.urdf or .yaml)")
    ex.add_argument("--data", default=None, metavar="FILE",
                    help="the measurement table the model was fitted on (default: the training file its "
                         "provenance names, if unchanged): its joint angles decide identifiability")
    ex.add_argument("--mapping", default=None, metavar="YAML", help="import mapping for a foreign --data file")
    ex.add_argument("--skip-bad", action="store_true", help="skip bad rows of --data instead of stopping")
    ex.add_argument("--name", default=None, help="the exported robot's name (default: <nominal>_calibrated)")
    ex.add_argument("--rtol", type=float, default=1e-5,
                    help="relative singular value below which a direction is not identifiable (default 1e-5)")
    ex.add_argument("--no-refine", action="store_true",
                    help="write the first-order parameter values (default: refined so that the exact chain "
                         "reaches the calibrated TCP; the first-order figures are reported either way)")
    add_output_args(ex)


def run(args: argparse.Namespace) -> Any:
    """Export the calibrated robot of a fitted model as a URDF or DH robot config, checked against the calibration.

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
    from dt_runtime.analysis.export import export_robot, model_of_twin

    model = args.model if args.model is not None else model_of_twin(args.twin)
    return export_robot(model, args.format, args.out, data=args.data, mapping=args.mapping,
                        skip_bad=args.skip_bad, rtol=args.rtol, name=args.name,
                        refine_fit=not args.no_refine)


def human(result: dict) -> str:
    """The text ``dt export`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    fk = result["fk_check"]
    out = [f"{result['format']} written to {result['out']} (loads back: "
           f"{', '.join(k for k, v in result['loads_back'].items() if v)})",
           f"{result['n_exported']} of {result['n_parameters']} geometric parameters identifiable "
           f"over {result['n_points']} joint configurations of {result['data']}:"]
    out += [f"  {p['name']} = {p['value']:.6g} {p['unit']}"
            + (f"  (absorbs {', '.join(p['absorbs'])})" if p["absorbs"] else "") for p in result["exported"]]
    out.append(f"not identifiable, not exported ({len(result['not_identifiable'])}): "
               + (", ".join(p["name"] for p in result["not_identifiable"]) or "none"))
    out.append("no effect on the TCP over the data: " + (", ".join(result["no_effect"]) or "none"))
    out += ["  aliases: " + " ~ ".join(g) for g in result["alias_groups"]]
    out.append(f"FK of the exported robot vs the calibrated FK: max {fk['max_mm']:.2e} mm, RMS {fk['rms_mm']:.2e} mm "
               f"({'within' if fk['ok'] else 'OVER'} {fk['tolerance_mm']} mm); first-order values alone: max "
               f"{fk['first_order_max_mm']:.2e} mm")
    out += [f"warning: {w}" for w in result["warnings"]]
    return "\n".join(out)
