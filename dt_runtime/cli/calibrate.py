"""`dt calibrate`: a twin from a campaign's measurement files, no simulator.

Registers the instruments' frames (three-line method), fits the error maps (the effects named
with --effects, or a `dt fit` model's configuration with --model, + GP; none: the paper's GPR),
computes the GUM budgets and the per-position uncertainty, validates on the validation file if
given, and writes the twin (OUT, for `dt run`, `dt correct`, `dt compare`) with OUT/summary.json
and OUT/report.html. The campaign: a directory with campaign.yaml (as `dt demo` writes in
DIR/campaign) or the files one by one; format in docs/campaign-files.md.

`--reference FILE --twin DIR` is the daily check instead: a deployed twin's session terms refitted
on a few reference poses of the new session, without recalibrating (docs/deployment.md).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dt_runtime.cli.common import (
    add_effects_file_arg,
    add_output_args,
    add_strict_arg,
    effects_catalogue,
    folds,
    names,
    parameter_lines,
    progress,
    seed_number,
    validity_exit,
)


def add_arguments(c: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt calibrate`` (docs/cli.md, ``dt calibrate``).

    Parameters
    ----------
    c : argparse.ArgumentParser
        The subcommand's parser.
    """
    c.add_argument("--campaign", default=None, metavar="DIR",
                   help="campaign directory (its campaign.yaml) or manifest; the options below override it")
    c.add_argument("--registration", default=None, metavar="FILE.csv", help="registration phase file")
    c.add_argument("--doe", default=None, metavar="FILE.csv", help="DOE phase file")
    c.add_argument("--validation", default=None, metavar="FILE.csv",
                   help="validation phase file, measured without correction (optional)")
    c.add_argument("--robot", default=None, metavar="ROBOT",
                   help="the robot: a catalogue arm (e.g. ur10e; `dt robots`), a robot config (e.g. "
                        "configs/robots/ur10.yaml) or a URDF; needed for joint-space effects")
    c.add_argument("--instruments", default=None, metavar="YAML",
                   help="instruments and certificates (e.g. configs/instruments_example.yaml), in the provenance")
    c.add_argument("--effects", default="", metavar="a,b,...",
                   help="physical effect terms of the e_LT map (default none: the paper's GPR)")
    add_effects_file_arg(c)
    c.add_argument("--gp-inputs", default="tcp_speed", choices=("tcp_speed", "tcp", "joints", "none"),
                   help="what the map's GP sees (default tcp_speed, the paper's)")
    c.add_argument("--model", default=None, metavar="MODEL",
                   help="take the e_LT map's configuration (effects, GP inputs and options, robot) from this "
                        "`dt fit` model; the map is refitted on the DOE so that its budget is the twin's")
    c.add_argument("--folds", type=folds, default=5, metavar="K", help="grouped cross-validation folds (default 5)")
    c.add_argument("--margin-mm", type=float, default=25.0, metavar="MM",
                   help="calibrated volume: the DOE hull widened by this margin (default 25 mm)")
    c.add_argument("--seed", type=seed_number, default=None,
                   help="seed of folds and GP restarts (default: the campaign manifest's, else 0)")
    c.add_argument("--out", default=None, metavar="TWIN",
                   help="twin directory to write (replaced whole at the end: an interrupted run leaves it as it was); "
                        "with --reference default --twin")
    c.add_argument("--reference", default=None, metavar="FILE.csv",
                   help="the daily check: reference poses measured at the start of a session (a phase file, "
                        "docs/campaign-files.md); refits the session terms of --twin without recalibrating")
    c.add_argument("--twin", default=None, metavar="TWIN", help="with --reference: the deployed twin to check")
    add_strict_arg(c)
    add_output_args(c)


def files_of(args: argparse.Namespace):
    """The campaign's files: the manifest's (``--campaign``) or ``--registration`` and ``--doe``, each
    overridden by its option; ``--robot`` overrides the robot.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    CampaignFiles

    Raises
    ------
    DataError
        When neither a campaign nor both files are given, or a named file does not exist.
    """
    from dataclasses import replace

    from dt_kernel.errors import DataError
    from dt_runtime.workflows.campaign_dir import CampaignFiles, read_manifest, resolve_robot

    def path(p: str | None) -> Path | None:
        if p is None:
            return None
        if not Path(p).is_file():
            raise DataError(f"{p}: no such file")
        return Path(p)

    if args.campaign:
        files = read_manifest(args.campaign)
    elif args.registration and args.doe:
        files = CampaignFiles(Path(args.registration), Path(args.doe))
    else:
        raise DataError("dt calibrate needs --campaign DIR, or --registration and --doe files")
    for k in ("registration", "doe", "validation", "instruments"):
        p = path(getattr(args, k))
        if p is not None:
            files = replace(files, **{k: p})  # type: ignore[arg-type]  # k names a Path field
    if args.robot:
        files = replace(files, robot=resolve_robot(args.robot, Path.cwd()))
    return files


def run(args: argparse.Namespace) -> Any:
    """Calibrate a twin from the campaign's files and write it with its summary and report.

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
    import dataclasses

    from pydantic import ValidationError

    from dt_kernel.errors import DataError
    from dt_runtime.common.outputs import staged
    from dt_runtime.models.hybrid import load_map
    from dt_runtime.reports.demo_report import write_demo_report  # matplotlib only when reporting
    from dt_runtime.workflows.calibrate import CalibrationOptions
    from dt_runtime.workflows.campaign_dir import calibrate_campaign

    if args.reference or args.twin:
        return _daily_check(args)
    if not args.out:
        raise DataError("dt calibrate needs --out TWIN (or --reference FILE --twin TWIN for the daily check)")
    files = files_of(args)
    cat = effects_catalogue(args)  # --effects may name --effects-file's effects
    seed = args.seed if args.seed is not None else files.seed if files.seed is not None else 0
    try:
        options = CalibrationOptions.model_validate(
            {"cv_folds": args.folds, "volume_margin_m": args.margin_mm / 1000.0, "effects": names(args.effects),
             "gp_inputs": args.gp_inputs, "seed": seed}, context={"catalogue": cat})
    except ValidationError as exc:
        err = exc.errors()[0]
        raise DataError(f"dt calibrate: {'.'.join(map(str, err['loc']))}: {err['msg']}") from exc
    lt_model = None
    if args.model:
        # the model's configuration as deployed: session terms are nuisance (one campaign here)
        lt_model = load_map(args.model, cat).unfitted(seed=seed, nuisance=())
        if files.robot is None and lt_model.robot is not None:
            files = dataclasses.replace(files, robot=str(lt_model.robot))
    prog = progress(args)
    inputs = [*files.inputs(), *([args.model] if args.model else [])]
    with staged(args.out, "dt calibrate", marks=("twin.json",), inputs=inputs) as out:  # whole or not at all
        res = calibrate_campaign(files, options, out, lt_model, args.model, prog, cat)
        write_demo_report(res, out / "report.html", title="Traceable digital twin of the cobot: calibration report")
    res.summary["report"] = str(Path(args.out) / "report.html")
    return res.summary


def _daily_check(args: argparse.Namespace) -> dict:
    """``--reference FILE --twin TWIN``: the daily check, the checked twin written whole (to --out, default TWIN)."""
    from dt_kernel.errors import DataError
    from dt_runtime.common.outputs import staged
    from dt_runtime.measurements.campaign_files import read_phase
    from dt_runtime.workflows import daily_check

    if not (args.reference and args.twin):
        raise DataError("the daily check needs both --reference FILE.csv and --twin TWIN")
    given = [f"--{k}" for k in ("campaign", "registration", "doe", "validation", "model") if getattr(args, k)]
    if given:
        raise DataError(f"--reference checks a deployed twin; {', '.join(given)} belong to a calibration")
    if not Path(args.reference).is_file():
        raise DataError(f"{args.reference}: no such file")
    if not (Path(args.twin) / "twin.json").is_file():
        raise DataError(f"{args.twin}: not a twin directory (no twin.json; `dt calibrate --out` writes one)")
    phase = read_phase(args.reference, "reference")
    summary, meta = daily_check.check(args.twin, phase, args.reference)
    out = args.out or args.twin
    with staged(out, "dt calibrate --reference", marks=("twin.json",), inputs=[args.reference]) as work:
        daily_check.write(args.twin, work, meta)  # the previous twin stays as it was until this is whole
    return {"daily_check": True, **summary, "written": str(out), "maps_refitted": False}


def _daily_lines(s: dict) -> list[str]:
    """The daily check's text: the frames' change with U, the terms tested and kept, the validity."""
    names = {"lt": "tracker frame T_lt", "mvs": "camera frame T_mvs"}
    lines = [f"daily check of {s['twin']} on {s['poses']} reference poses ({s['distinct_points']} distinct points) "
             f"of {s['reference']}"]
    for k, f in s["frames"].items():
        lines.append(f"  {names[k]} refitted: moved " + ", ".join(
            f"{v:+.3f} ± {u:.3f}" for v, u in zip(f["translation_mm"], f["translation_U_mm"])) + " mm, turned "
            + ", ".join(f"{v:+.3f} ± {u:.3f}" for v, u in zip(f["rotation_mrad"], f["rotation_U_mrad"]))
            + f" mrad (U95, k = {f['k']:.2f}); residual {f['residual_rms_mm']:.3f} mm RMS; "
            + ("a significant change" if f["p_value_no_change"] < 0.01 else "no significant change")
            + f" (p = {f['p_value_no_change']:.2g})")
    lines += [f"  {t['text']}" for t in s["terms"] if t["identified"]]
    lines += [f"  kept: {k}" for k in s["kept"]]
    lo = s["leave_one_out"]
    lines.append(f"  each pose scored by the frames fitted on the other {lo['n'] - 1} (a small sample): 3D RMS "
                 f"{lo['rms_mm']:.3f} mm, U95 covers " + ", ".join(f"{ax} {100 * v:.0f} %"
                                                                   for ax, v in lo["coverage_95"].items())
                 + ("; fails Eq. 17 " + ", ".join(f"{ax} {100 * v:.0f} %"
                                                  for ax, v in lo["eq17_failures_per_axis"].items())
                    if lo["eq17_failures_per_axis"] else "; no camera points: Eq. 17 not checked"))
    lines.append(f"twin written to {s['written']} with the new frames and their uncertainty (error maps not refitted)")
    changed = [t["term"] for t in s["terms"] if t.get("changed")]
    ok = s["validity"]["status"] == "ok" and not changed
    lines.append("next: " + ("the twin is ready for this session (dt run, dt correct)" if ok else
                             ("recalibrate (dt calibrate --campaign): the session's " + " and ".join(changed)
                              + " changed, which the maps cannot take up") if changed else
                             "measure the reference poses again; if it stays, recalibrate (dt calibrate --campaign)"))
    lines.append(s["validity"]["line"])
    return lines


def human(s: dict) -> str:
    """The text ``dt calibrate`` prints without ``--json``.

    Parameters
    ----------
    s : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    if s.get("daily_check"):
        return "\n".join(_daily_lines(s))
    e = s["maps"]["e_lt"]
    lines = [f"twin written to {s['twin']} (e_LT map: {', '.join(e['effects']) + ' + GP' if e['effects'] else 'GPR'})",
             f"precision (Sect. 3.3): {s['precision_before_mm']:.3f} mm -> {s['precision_after_mm']:.3f} mm "
             f"({s['improvement_pct']:.1f} % better)"]
    if e["parameters"]:
        lines.append("effect parameters of the e_LT map (the short base-parameter table):")
        lines += ["  " + ln for ln in parameter_lines(e["parameters"], e.get("base_parameters"))]
    uc = s.get("uncertainty_calibration")
    if uc:
        lines.append(f"U(TCP_c) calibrated on held-out data: {uc['method']}, {uc['n']} target points, factor "
                     + " ".join(f"{ax} {f:.3f}" for ax, f in zip("xyz", uc["factor"])) + f" ({uc['guarantee']})")
    v = s.get("validation")
    if v and v["n"]:
        cov = v["coverage_95"]
        lines.append(f"validation ({v['n']} positionings): tracker error {v['rms_e_lt_mm']:.4f} mm 3D RMS, "
                     f"{v['rms_after_map_mm']:.4f} mm after the map ({v['reduction_pct']:.1f} % lower); coverage "
                     f"of U(TCP_c): x {cov['x']:.1%}, y {cov['y']:.1%}, z {cov['z']:.1%}")
    lines.append(f"report: {s['report']}")
    lines.append(s["validity"]["line"])
    return "\n".join(lines)


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
