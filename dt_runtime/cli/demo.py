"""`dt demo`: the paper's whole experiment on the simulated cell, and its report.

Registration, DOE, GPR, uncertainty budget, validation and t-test on the simulated cell; writes
DIR/summary.json, DIR/report.html, the campaign files DIR/campaign and the twin DIR/model, all at
once at the end (an interrupted run leaves a previous DIR as it was).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dt_runtime.cli.common import add_strict_arg, progress, seed_number, validity_exit
from dt_runtime.common.outputs import staged

MARKS = ("summary.json", "report.html", "model", "campaign")  # what a previous `dt demo --out DIR` left


def add_arguments(d: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt demo`` (docs/cli.md, ``dt demo``).

    Parameters
    ----------
    d : argparse.ArgumentParser
        The subcommand's parser.
    """
    d.add_argument("--out", default="out/demo", metavar="DIR",
                   help="output directory (default out/demo), replaced whole at the end of the run")
    d.add_argument("--quick", action="store_true", help="reduced plan, well under a minute")
    d.add_argument("--seed", type=seed_number, default=None, help="plan seed (default: the plan config's)")
    d.add_argument("--config", default=None, help="demo config YAML (default: configs/demo.yaml)")
    d.add_argument("--camera", default=None, metavar="DRIVER",
                   help="camera driver, overriding the config (sim_images or sim_point)")
    add_strict_arg(d)
    d.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    d.add_argument("--no-progress", action="store_true", help="do not show progress on stderr")


def run(args: argparse.Namespace) -> Any:
    """Run the paper's experiment on the simulated cell and write its campaign, twin, summary and report.

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
    from dt_runtime.reports.demo_report import write_demo_report  # matplotlib only when reporting
    from dt_runtime.workflows.demo import run_demo

    prog = progress(args)
    # written whole or not at all (common.outputs)
    with staged(args.out, "dt demo", marks=MARKS, inputs=[args.config] if args.config else []) as out:
        res = run_demo(out, quick=args.quick, seed=args.seed, config=args.config,
                       progress=prog, camera=args.camera)
        write_demo_report(res, out / "report.html")
    prog.note(f"wrote {Path(args.out) / 'report.html'}")
    return res.summary


def _where(s: dict) -> str:
    """What `coverage_95` was measured at: the random targets inside the DOE hull, or (without
    that check) the corrected validation positionings."""
    chk = s.get("coverage_check") or {}
    if "inside" in chk:
        return f"{chk['inside']['n']} random targets inside the DOE hull"
    return f"the {s.get('n_validation', '?')} corrected validation positionings"


def human(s: dict) -> str:
    """The text ``dt demo`` prints without ``--json``.

    Parameters
    ----------
    s : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    cov = s["coverage_95"]
    lines = [
        f"precision (Sect. 3.3): {s['precision_before_mm']:.3f} mm -> {s['precision_after_mm']:.3f} mm "
        f"({s['improvement_pct']:.1f} % better; paper: 0.970 -> 0.216 mm, 77.8 %)",
        f"true 3D RMS error at validation targets: {s['true_rms_uncorrected_mm']:.3f} mm uncorrected -> "
        f"{s['true_rms_corrected_mm']:.3f} mm corrected ({s['true_error_reduction_pct']:.1f} % lower)",
        f"coverage of the per-position U(TCP_c) (95 %) at {_where(s)}: "
        f"x {cov['x']:.1%}, y {cov['y']:.1%}, z {cov['z']:.1%}",
    ]
    out = s.get("coverage_95_outside")
    if out:
        lines.append(f"... and 50-150 mm outside it: x {out['x']:.1%}, y {out['y']:.1%}, z {out['z']:.1%}; "
                     f"mean U outside / inside {s['u_ratio_outside_inside']:.2f}")
    lines.append(f"Eq. 17 t-test pass fraction: {s['t_test_eq17']['pass_fraction_all_axes']:.1%}")
    if s.get("twin"):
        out_dir = Path(s["twin"]).parent
        lines.append(f"wrote {out_dir / 'report.html'}, {out_dir / 'summary.json'} and the twin {s['twin']}")
    lines.append(s["validity"]["line"])
    return "\n".join(x for x in lines if x)


def exit_code(args: argparse.Namespace, summary: dict) -> int:
    """The exit status: 0, or STRICT_EXIT with ``--strict`` when the validity check failed.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.
    summary : dict
        What ``run`` returned.

    Returns
    -------
    int
    """
    return validity_exit(args, summary)
