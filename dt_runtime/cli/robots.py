"""`dt robots`: the catalogue of nominal kinematics (configs/robots/catalogue/), each arm with
its number of joints, vendor and the source its numbers were read from.

Any command's --robot takes one of these names (e.g. --robot ur5e), a robot config YAML or a
URDF (arm.urdf, arm.urdf#tool0); docs/robots.md.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import add_output_args


def add_arguments(r: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt robots`` (docs/cli.md, ``dt robots``).

    Parameters
    ----------
    r : argparse.ArgumentParser
        The subcommand's parser.
    """
    add_output_args(r)


def run(args: argparse.Namespace) -> Any:
    """List the catalogue of nominal kinematics.

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
    from dt_runtime.frames.robots import catalogue

    return {"robots": [e.to_dict() for e in catalogue()]}


def human(result: dict) -> str:
    """The text ``dt robots`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    rows = [f"{r['name']:<16} {r['dof']} axes  {r['vendor']}: {r['description']}\n"
            + "\n".join(f"{'':<16} source: {s['title']} ({s['version']})" for s in r["sources"])
            for r in result["robots"]]
    return "\n".join(rows) + "\n(--robot NAME in any command; docs/robots.md)"
