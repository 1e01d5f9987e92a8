"""`dt compare`: error models against measurements, side by side, and where they fail.

RMS, mean and max 3D error, per axis, Eq. 17 t-test failures and the residual broken down by
region, speed, payload, temperature, time and joint configuration, for 'as is' and every --model
in the order given; the last model's effect parameters as the short base-parameter table.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import (
    add_data_args,
    add_effects_file_arg,
    add_mpe_arg,
    add_output_args,
    add_strict_arg,
    cv_folds,
    effects_catalogue,
    input_files,
    load,
    names,
    parameter_lines,
    progress,
    validity_exit,
)


def add_arguments(cp: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt compare`` (docs/cli.md, ``dt compare``).

    Parameters
    ----------
    cp : argparse.ArgumentParser
        The subcommand's parser.
    """
    add_data_args(cp, kinematics=False)
    cp.add_argument("--model", required=True, action="append", metavar="MODEL",
                    help="model directory from `dt fit`; repeat for a side-by-side comparison (oldest first)")
    cp.add_argument("--names", default="", metavar="a,b,...",
                    help="column names of the models (default: directory names)")
    cp.add_argument("--cv", type=cv_folds, default=0, metavar="K",
                    help="held-out figures from the training file: refit each model's configuration on K-1 "
                         "folds grouped by target point (default 0: the models as saved)")
    cp.add_argument("--report", default=None, metavar="DIR",
                    help="write DIR/report.html and DIR/compare.json (DIR replaced whole at the end)")
    cp.add_argument("--reference", type=_reference, default=None, metavar="K",
                    help="reference poses per new session: its registration refitted on K poses spread over its "
                         "points, with the model's correction applied, and every other row scored after it (Eq. 17 "
                         "with the registration's uncertainty, coverage of U95). Default: 10 for sessions whose "
                         "registration was fitted on their own points (measured_frame: instrument); K > 0: every "
                         "session no model was trained on; 0: off")
    add_strict_arg(cp)
    add_effects_file_arg(cp)
    cp.add_argument("--instruments", default=None, metavar="YAML",
                    help="the campaign's instruments and certificates (e.g. configs/instruments_example.yaml), "
                         "recorded in the provenance")
    add_mpe_arg(cp)
    add_output_args(cp)


def _reference(text: str) -> int:
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of reference poses") from None
    if k != 0 and k < 3:
        raise argparse.ArgumentTypeError(f"{k}: a registration needs at least 3 reference poses (0: off)")
    return k


def run(args: argparse.Namespace) -> Any:
    """Evaluate 'as is' and every ``--model`` on the data, side by side, and write the report when asked.

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
    from pathlib import Path

    from dt_runtime.analysis.compare import compare
    from dt_runtime.analysis.data import floor_of, refit_sessions
    from dt_runtime.cli.common import data_inputs
    from dt_runtime.common.jsonsafe import jsonable
    from dt_runtime.common.outputs import staged

    cat = effects_catalogue(args)
    d = load(args, cat)
    # --report: report.html and compare.json written whole or not at all (common.outputs); a
    # directory it may not replace is refused before the comparison runs
    with (staged(args.report, "dt compare", marks=("compare.json", "report.html"), inputs=data_inputs(args))
          if args.report else contextlib.nullcontext()) as report_dir:
        result, arrays = compare(args.model, d.dataset, names(args.names) or None, noise_floor_m=floor_of(d),
                                 cv_folds=args.cv, seed=args.seed, progress=progress(args),
                                 instruments=args.instruments, inputs=input_files(args),
                                 refit_sessions=refit_sessions(d), sessions=d.info.get("session_files"),
                                 catalogue=cat, reference=args.reference)
        result = jsonable(result) | {k: v for k, v in d.info.items() if k not in ("n", "data")}
        if report_dir is not None:
            from dt_runtime.reports.compare_report import write_compare_report  # matplotlib only when reporting

            result["report"] = str(Path(args.report) / "report.html")
            write_compare_report(result, arrays, report_dir)
    return result


def human(result: dict) -> str:
    """The text ``dt compare`` prints without ``--json``.

    Parameters
    ----------
    result : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    lines = [f"{result['n']} rows of {result['dataset']}"
             + (f"; held out by {result['heldout']['folds']}-fold grouped CV" if result.get("heldout") else "")
             + (f"; noise floor {result['noise_floor_mm']:.4f} mm" if result.get("noise_floor_mm") else "")]
    for m in result["models"]:
        f = m.get("failures")
        lines.append(f"  {m['name']:<24} 3D RMS {m['rmse_mm']:.4f} mm  mean {m['mae_mm']:.4f}  max {m['max_mm']:.4f}"
                     + (f"  fails Eq. 17: {100 * f['fraction']:.1f} %" if f else ""))
        if m.get("after_reregistration"):
            rr = m["after_reregistration"]
            lines.append(f"  {'':<24} after re-registration ({rr['dof_absorbed']} dof absorbed): 3D RMS "
                         f"{rr['rmse_mm']:.4f} mm")
        lines += _registration_lines(m.get("after_registration"))
        if m.get("time_terms"):
            lines.append(f"  {'':<24} {m['time_terms']['text']}")
    lines += _session_lines(result["models"])
    for c in result.get("worst_cells") or []:
        lines.append(f"  worst: {c['factor']} {c['cell']}: {c['rmse_mm']:.4f} mm ({c['n']} rows)")
    primary = result["models"][-1] if result.get("models") else {}
    if primary.get("parameters"):  # the primary model's effect parameters, as `dt fit` prints them
        lines.append(f"effect parameters of {primary['name']} (as trained):")
        lines += ["  " + ln for ln in parameter_lines(primary["parameters"], primary.get("base_parameters"))]
    if result.get("conformal"):
        c = result["conformal"]
        lines.append(f"conformal factor of U95 ({c['method']}, {c['n']} held-out points): "
                     + " ".join(f"{ax} {f:.3f}" for ax, f in zip("xyz", c["factor"]))
                     + "; coverage with it (cross-fitted) " + _pcts(c["coverage_95_conformal_cross_fitted"])
                     + ", without " + _pcts(c["coverage_95_gum"]))
    if result.get("report"):
        lines.append(f"report: {result['report']}")
    if result.get("validity"):
        lines.append(result["validity"]["line"])
    return "\n".join(lines)


def _pcts(d: dict) -> str:
    return " ".join(f"{ax} {100 * v:.0f} %" for ax, v in d.items())


def _registration_lines(ar: dict | None) -> list[str]:
    """A new session registered on reference poses: the rows scored before and after."""
    if not ar:
        return []
    out = []
    if ar["n"]:
        b = ar["before"]
        out.append(f"  {'':<24} new session(s) registered on {ar['reference_poses']} reference poses, the other "
                   f"{ar['n']} rows: 3D RMS {b['rmse_mm']:.4f} -> {ar['rmse_mm']:.4f} mm; fails Eq. 17 "
                   f"{_pcts(b['failures_per_axis'])} -> {_pcts(ar['failures_per_axis'])}; U95 covers "
                   f"{_pcts(b['coverage_95'])} -> {_pcts(ar['coverage_95'])}")
    out += [f"  {'':<24} session {x.get('name') or x['session']} not registered: {x['why']}" for x in ar["skipped"]]
    return out


def _session_cell(x: dict) -> str:
    rr = x.get("after_reregistration")
    f = (rr or x).get("failures")
    return (f"{x['rmse_mm']:.4f}" + (f" [{rr['rmse_mm']:.4f}]" if rr else "")
            + (f" {100 * f['fraction']:.1f} %" if f else "") + (" *" if x.get("in_sample") else ""))


def _session_lines(models: list[dict]) -> list[str]:
    """Data of several sessions: one line per session, one cell per model (as is first)."""
    if not models or not models[0].get("sessions"):
        return []
    rr = any(x.get("after_reregistration") for m in models for x in m["sessions"])
    names = [x.get("name") or f"session {x['session']}" for x in models[0]["sessions"]]
    cells = [[_session_cell(x) for x in m["sessions"]] for m in models]
    w = max(len(n) for n in [*names, "session"])
    cw = [max(len(m["name"]), *(len(c) for c in col)) for m, col in zip(models, cells)]

    def line(first: str, rows: str, texts: list[str]) -> str:
        return (f"    {first:<{w}}  {rows:>5}  " + "  ".join(f"{t:<{c}}" for t, c in zip(texts, cw))).rstrip()

    out = ["  per session: 3D RMS / mm" + (", [after re-registration]" if rr else "")
           + ", fraction failing Eq. 17" + (" (after re-registration)" if rr else ""),
           line("session", "rows", [m["name"] for m in models])]
    out += [line(name, str(x["n"]), [col[i] for col in cells])
            for i, (name, x) in enumerate(zip(names, models[0]["sessions"]))]
    if any(x.get("in_sample") for m in models for x in m["sessions"]):
        out.append("    * in-sample: the model was trained on this session's file")
    return out


def exit_code(args: argparse.Namespace, result: dict) -> int:
    """0, or with --strict the strict status when the validity check fails (cli.common.validity_exit).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.
    result : dict
        The comparison's JSON object.

    Returns
    -------
    int
    """
    return validity_exit(args, result)
