"""`dt calibrate`: a twin from a campaign's measurement files, no simulator.

Registers the instruments' frames (three-line method), fits the error maps (the effects named
with --effects, or a `dt fit` model's configuration with --model, + GP; none: the paper's GPR),
computes the GUM budgets and the per-position uncertainty, validates on the validation file if
given, and writes the twin (OUT, for `dt run`, `dt correct`, `dt compare`) with OUT/summary.json
and OUT/report.html. The campaign: a directory with campaign.yaml (as `dt demo` writes in
DIR/campaign) or the files one by one; format in docs/campaign-files.md.
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
    c.add_argument("--out", required=True, metavar="TWIN",
                   help="twin directory to write (replaced whole at the end: an interrupted run leaves it as it was)")
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
