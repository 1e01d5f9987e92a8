"""`dt campaign`: run the calibration campaign on the cell of a runtime YAML, then calibrate.

The drivers are the runtime YAML's (`drivers:`, exactly as `dt run` builds them: a real cell,
the emulated cell of `python -m emulators.emulated_cell`, or the simulated drivers), so the twin
is calibrated with the instruments the daemon will use. Phase 1 (registration) and phase 2 (the
DOE) of the plan are measured through them and written as a campaign directory (OUT/campaign,
docs/campaign-files.md, its manifest naming the drivers); `dt calibrate` then makes the twin in
OUT/model, the directory a runtime YAML's `twin:` names. `--doe-rows N` measures N DOE rows
spread evenly through the plan (a short campaign: a smoke test of a cell, not a calibration).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dt_runtime.cli.common import add_output_args, folds, progress


def add_arguments(c: argparse.ArgumentParser) -> None:
    """Declare the arguments of ``dt campaign`` (docs/cli.md, ``dt campaign``).

    Parameters
    ----------
    c : argparse.ArgumentParser
        The subcommand's parser.
    """
    c.add_argument("--config", required=True, metavar="YAML", help="runtime YAML: its drivers and sim sections")
    c.add_argument("--plan", default="plan_quick.yaml", metavar="YAML",
                   help="experiment plan (default configs/plan_quick.yaml)")
    c.add_argument("--doe-rows", type=int, default=None, metavar="N",
                   help="measure only N DOE rows, spread evenly through the plan")
    c.add_argument("--folds", type=folds, default=5, metavar="K", help="grouped cross-validation folds (default 5)")
    c.add_argument("--out", required=True, metavar="DIR",
                   help="writes DIR/campaign and the twin DIR/model (DIR replaced whole at the end of the run)")
    add_output_args(c)


def run(args: argparse.Namespace) -> Any:

    """Measure the plan's registration and DOE through the runtime YAML's drivers, then calibrate the twin.

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
    from dt_kernel.errors import DataError
    from dt_runtime.common.outputs import staged
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.measurements.plans import build_plan, load_plan
    from dt_runtime.service.runtime_config import load_runtime_config

    config = Path(args.config)
    cfg = load_runtime_config(config)  # every driver's options checked before anything opens
    plan_file = Path(args.plan) if Path(args.plan).is_file() else CONFIGS / args.plan
    plan_cfg = load_plan(plan_file)
    plan = build_plan(plan_cfg)
    doe = plan.doe
    if args.doe_rows is not None:
        if not 1 <= args.doe_rows <= len(doe):
            raise DataError(f"--doe-rows {args.doe_rows}: the plan has {len(doe)} DOE rows")
        doe = spread(doe, args.doe_rows)
    prog = progress(args)
    names = {k: n for k, n, _ in cfg.drivers.chosen()}
    with staged(args.out, "dt campaign", marks=("campaign", "model"), inputs=[config]) as out:  # whole or not at all
        return _measure_and_calibrate(args, cfg, config, plan, plan_cfg, doe, names, out, prog)


def _measure_and_calibrate(args, cfg, config: Path, plan, plan_cfg, doe: list, names: dict, out: Path, prog) -> dict:
    """Phases 1 and 2 through the runtime YAML's drivers, written as OUT/campaign; the twin in OUT/model."""
    from dt_runtime.common.outputs import final_path
    from dt_runtime.workflows.calibrate import CalibrationOptions, Campaign
    from dt_runtime.workflows.campaign import Instruments, run_rows
    from dt_runtime.workflows.campaign_dir import calibrate_campaign, write_campaign

    world = _world(cfg, config.parent)
    try:
        robot, tracker, camera = cfg.drivers.create(world, str(config))
        inst = Instruments(robot, tracker, camera, world=world,
                           max_speed=world.max_speed() if world else cfg.limits.max_speed_m_s)
        try:
            inst.activate()
            reg = run_rows(inst, plan.registration, prog, "phase 1 registration")
            doe_data = run_rows(inst, doe, prog, "phase 2 DOE")
        finally:
            inst.close()
    finally:
        if world is not None:
            world.close()
    files = write_campaign(out / "campaign", Campaign(reg, doe_data), None, plan_cfg.seed, (), names,
                           f"dt campaign, {config.name}, drivers {names}")
    options = CalibrationOptions(cv_folds=args.folds, seed=plan_cfg.seed)
    res = calibrate_campaign(files, options, out / "model", progress=prog)
    refusals = reg.refusals + doe_data.refusals
    return {"campaign": str(final_path(files.manifest or files.doe)), "twin": str(final_path(out / "model")),
            "drivers": names,
            "registration_rows": reg.n, "doe_rows": doe_data.n, "refusals": len(refusals),
            "refusal_examples": refusals[:5],
            "registration_residuals_mm": res.summary.get("table2_registration_residuals"),
            "e_lt_doe_mm": res.summary.get("table3_as_is", {}).get("e_lt_doe"),
            "precision_before_mm": res.summary.get("precision_before_mm"),
            "precision_after_mm": res.summary.get("precision_after_mm")}


def spread(rows: list, n: int) -> list:
    """``n`` of ``rows``, evenly spaced through them (first and last included): a short DOE that
    still spans the plan's volume and speeds.

    Parameters
    ----------
    rows : list
    n : int

    Returns
    -------
    list
    """
    import numpy as np

    return [rows[int(i)] for i in np.linspace(0, len(rows) - 1, n).round()]


def _world(cfg, base: Path):
    """The simulated cell when a chosen driver runs on one (as `dt run` builds it), else None."""
    from drivers import registry

    if not any(registry.needs_world(k, n) for k, n, _ in cfg.drivers.chosen()):
        return None
    from drivers.simulated.devices import SimWorld
    from dt_runtime.common.paths import beside
    from dt_runtime.workflows.simulate import load_scenario_file

    p = lambda rel: beside(base, rel)  # noqa: E731
    scenario, _ = load_scenario_file(p(cfg.sim.scenario))
    return SimWorld(scenario, p(cfg.sim.cell), source=str(p(cfg.sim.scenario)))


def human(s: dict) -> str:
    """The text ``dt campaign`` prints without ``--json``.

    Parameters
    ----------
    s : dict
        What ``run`` returned.

    Returns
    -------
    str
    """
    return (f"campaign {s['campaign']} ({s['registration_rows']} registration, {s['doe_rows']} DOE rows, "
            f"{s['refusals']} refusals; drivers {s['drivers']}); twin {s['twin']}: precision "
            f"{s['precision_before_mm']:.3f} mm -> {s['precision_after_mm']:.3f} mm")
