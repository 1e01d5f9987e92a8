"""`dt correct`: a whole program corrected offline, with the uncertainty of every position.

For every target of a program file (x, y, z in mm, speed in mm/s, optional point_id), the twin's
corrected command, the expanded uncertainty (95 %) of the position it reaches and whether it
lies in the calibrated volume (the DOE's hull plus its margin). A path program (`--path`: lines
and arcs, or timed poses, `programs.path`) is interpolated at `--rate` and every set-point corrected
the same way (`programs.path_correct`).
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_kernel.units import MM_PER_M


def add_arguments(c: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt correct`` (docs/cli.md, ``dt correct``).

    Parameters
    ----------
    c : argparse.ArgumentParser
        The subcommand's parser.
    """
    c.add_argument("--twin", required=True, metavar="TWIN", help="twin directory (e.g. out/demo/model from dt demo)")
    src = c.add_mutually_exclusive_group(required=True)
    src.add_argument("--targets", metavar="FILE.csv", help="a point program: x, y, z (mm), speed (mm/s)")
    src.add_argument("--path", metavar="FILE.yaml", help="a path program: lines and arcs (or timed poses) with speed "
                     "and acceleration limits (docs/cli.md, 'Path programs')")
    c.add_argument("--rate", type=float, default=500.0, metavar="HZ",
                   help="with --path: the controller's set-point rate (default 500; a CB3 UR: 125)")
    c.add_argument("--out", required=True, metavar="FILE.csv",
                   help="the corrected program, or with --path the set-point table (written atomically)")
    c.add_argument("--refuse-outside", action="store_true",
                   help="exit with an error, writing nothing, if any command lies outside the calibrated volume")
    c.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> Any:
    """Correct every target of a program (or every set-point of a path) with the twin and write the corrected file.

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
    import numpy as np

    from dt_kernel.errors import DataError
    from dt_runtime.programs.program import correct_program, read_program, write_corrected
    from dt_runtime.twin.twin import Twin

    twin = Twin.load(args.twin)
    if args.path is not None:
        return _run_path(args, twin)
    prog = read_program(args.targets, twin.needs)  # with the columns a declared effect reads
    corr = correct_program(twin, prog)
    outside = [i for i, c in enumerate(corr) if not c.inside]
    if args.refuse_outside and outside:
        first = ", ".join(f"{prog.point_id[i]} (line {prog.line[i]})" for i in outside[:5])
        raise DataError(f"{args.targets}: {len(outside)} of {prog.n} targets need a command outside the calibrated "
                        f"volume: {first}{' ...' if len(outside) > 5 else ''}; nothing written")
    path = write_corrected(args.out, prog, corr)
    U = np.array([c.U for c in corr])
    return {"out": str(path), "n": prog.n, "n_outside": len(outside), "twin": str(args.twin),
            "max_U_mm": [round(float(x) * MM_PER_M, 4) for x in U.max(axis=0)],
            "mean_U_mm": [round(float(x) * MM_PER_M, 4) for x in U.mean(axis=0)],
            "max_correction_mm": round(float(max(np.linalg.norm(c.command - c.target) for c in corr)) * MM_PER_M, 4)}


def _run_path(args: argparse.Namespace, twin) -> dict:
    import numpy as np

    from dt_kernel.errors import DataError
    from dt_runtime.programs.path import interpolate, read_path
    from dt_runtime.programs.path_correct import correct_path, label, write_setpoints

    path = read_path(args.path)
    sp = interpolate(path, args.rate)
    corr = correct_path(twin, path, sp)
    outside = [k for k, c in enumerate(corr) if not c.inside]
    if args.refuse_outside and outside:
        first = ", ".join(label(sp, k) for k in outside[:3])
        raise DataError(f"{args.path}: {len(outside)} of {sp.n} set-points need a command outside the calibrated "
                        f"volume: {first}{' ...' if len(outside) > 3 else ''}; nothing written")
    out = write_setpoints(args.out, sp, corr)
    U = np.array([c.U for c in corr])
    return {"out": str(out), "kind": "path", "n": sp.n, "n_outside": len(outside), "twin": str(args.twin),
            "rate_hz": sp.rate_hz, "duration_s": round(float(sp.t[-1]), 6), "segments": int(sp.segment.max()) + 1,
            "max_speed_mm_s": round(float(sp.speed.max()) * MM_PER_M, 3),
            "max_U_mm": [round(float(x) * MM_PER_M, 4) for x in U.max(axis=0)],
            "mean_U_mm": [round(float(x) * MM_PER_M, 4) for x in U.mean(axis=0)],
            "max_correction_mm": round(float(np.max(np.linalg.norm(np.array([c.command for c in corr]) - sp.p,
                                                                   axis=1))) * MM_PER_M, 4)}


def human(r: dict) -> str:
    """The text ``dt correct`` prints without ``--json``.

    Parameters
    ----------
    r : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    if r.get("kind") == "path":
        return (f"{r['n']} set-points ({r['segments']} segments, {r['duration_s']} s at {r['rate_hz']:g} Hz) "
                f"corrected -> {r['out']}; {r['n_outside']} outside the calibrated volume; "
                f"U (95 %) mean {r['mean_U_mm']} mm, max {r['max_U_mm']} mm; "
                f"largest correction {r['max_correction_mm']} mm")
    return (f"{r['n']} targets corrected -> {r['out']}; {r['n_outside']} outside the calibrated volume; "
            f"U (95 %) mean {r['mean_U_mm']} mm, max {r['max_U_mm']} mm; "
            f"largest correction {r['max_correction_mm']} mm")
