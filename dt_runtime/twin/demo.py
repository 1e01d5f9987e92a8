"""`dt demo`: the paper's whole experiment on the simulated cell, end to end.

Registration (phase 1), DOE (phase 2), GPR training, uncertainty budget, validation (phase 3)
with uncorrected and corrected commands, the Eq. 17 t-test, and scoring against the simulator's
truth. Writes DIR/summary.json and the twin (DIR/model); the command line adds DIR/report.html
(reports sit above the twin layer).
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import Field

from drivers import registry
from drivers.simulated.devices import SimWorld
from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import UnreachableError
from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.common.paths import CONFIGS
from dt_runtime.common.progress import Progress
from dt_runtime.common.provenance import Instrument, Provenance
from dt_runtime.common.provenance import build as build_provenance
from dt_runtime.frames.volume import CalibratedVolume
from dt_runtime.measurements.phase import PhaseData
from dt_runtime.measurements.plans import build_plan, load_plan
from dt_runtime.metrology import uncertainty as unc
from dt_runtime.metrology.stats import mean_std_mm, rms3
from dt_runtime.twin import calibration as cal
from dt_runtime.twin.campaign import Instruments, check_reachable, run_rows
from dt_runtime.twin.coverage_check import CoverageCheck, run_check, sample_targets


class DriversConfig(Frozen):
    robot: str = "sim"
    tracker: str = "sim"
    camera: str = "sim_point"


class DemoConfig(Frozen):
    scenario: str
    cell: str
    plan: str
    quick_plan: str
    drivers: DriversConfig = DriversConfig()
    cv_folds: int = 5
    # The calibrated volume: the DOE's convex hull widened by this margin (m); beyond it a
    # correction is flagged as extrapolation.
    volume_margin_m: float = Field(0.025, ge=0.0, le=0.5)
    # Distinct random targets inside the DOE hull and in a band 50-150 mm outside it, commanded
    # corrected and scored against the simulator's truth (coverage of the per-position U).
    coverage_targets: int = Field(200, ge=0, le=5000)


@dataclass
class DemoResult:
    summary: dict
    arrays: dict = field(default_factory=dict)  # raw arrays for the report figures (SI units)


def _open(cfg: DemoConfig, base: Path, seed: int | None) -> tuple[Instruments, SimWorld]:  # noqa: ARG001
    """The activated instruments and the simulated world behind them (typed: Instruments.world is not)."""
    world = SimWorld(base / cfg.scenario, base / cfg.cell)
    src = str(base / "demo.yaml")
    robot = registry.create("robot", cfg.drivers.robot, source=src, world=world)
    tracker = registry.create("tracker", cfg.drivers.tracker, source=src, world=world)
    camera = registry.create("camera", cfg.drivers.camera, source=src, world=world)
    inst = Instruments(robot, tracker, camera, world=world, max_speed=world.max_speed())
    inst.activate()
    return inst, world


def run_demo(out: str | Path, quick: bool = False, seed: int | None = None,
             config: str | Path | None = None, progress: Progress | None = None,
             camera: str | None = None) -> DemoResult:
    t0 = time.monotonic()
    progress = progress or Progress(enabled=False)
    config = Path(config) if config else CONFIGS / "demo.yaml"
    cfg = load_yaml(config, DemoConfig)
    if camera:
        cfg = cfg.model_copy(update={"drivers": cfg.drivers.model_copy(update={"camera": camera})})
    base = config.parent
    plan_file = base / (cfg.quick_plan if quick else cfg.plan)
    plan_cfg = load_plan(plan_file)
    if seed is not None:
        plan_cfg = plan_cfg.model_copy(update={"seed": seed})
    plan = build_plan(plan_cfg)
    seed = plan_cfg.seed
    inst, world = _open(cfg, base, seed)
    try:
        targets = np.array([r.target for r in plan.registration + plan.doe + plan.validation])
        check_reachable(world, targets)
        progress.note(f"plan: {len(plan.registration)} registration, {len(plan.doe)} DOE, "
                      f"{len(plan.validation)} validation positionings")
        reg_data = run_rows(inst, plan.registration, progress, "phase 1 registration")
        frames = cal.register(reg_data)
        doe_data = run_rows(inst, plan.doe, progress, "phase 2 DOE")
        doe = cal.doe_errors(doe_data, frames)
        progress.note("training GPR models e_LT(TCP, v) and e_MVS-LT(TCP, v), grouped cross-validation")
        maps = cal.fit_models(doe, cfg.cv_folds, seed)
        e_lt, e_mvs_lt, r_lt, r_mvs_lt = maps.e_lt, maps.e_mvs_lt, maps.r_lt, maps.r_mvs_lt
        lt_dist = float(np.median(np.linalg.norm(doe_data.p_lt[np.all(np.isfinite(doe_data.p_lt), 1)], axis=1)))
        speed = doe.X[:, 3]
        inp = cal.metrology_inputs(frames, cal.replicate_means(r_lt, doe.groups, speed),
                                   cal.replicate_means(r_mvs_lt, doe.groups, speed), lt_dist)
        budgets = cal.budgets(inp)
        literal = cal.budgets(dataclasses.replace(inp, registration_term="spread"))
        progress.note("per-position uncertainty: held-out calibration of the GP's std, leave-a-face-out extrapolation")
        twin = cal.make_twin(frames, e_lt, e_mvs_lt, budgets, cfg.drivers.model_dump(),
                             CalibratedVolume.of_points(doe.X[:, :3], cfg.volume_margin_m),
                             cal.position_uncertainty(budgets["eq11_tcp_c"], doe, maps, seed))
        val_plain = run_rows(inst, plan.validation, progress, "phase 3 validation, uncorrected")
        val_corr = run_rows(inst, plan.validation, progress, "phase 3 validation, corrected",
                            command=twin.corrected_command)
        checks = _coverage_checks(inst, twin, doe, plan_cfg.doe_speeds, cfg.coverage_targets, seed, world, progress)
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        prov = demo_provenance(cfg, config, plan_file, inst, world, (reg_data, doe_data, val_plain, val_corr))
        twin.provenance = prov
        twin.save(out / "model")
        result = _summarise(plan_cfg, quick, frames, doe, r_lt, r_mvs_lt, budgets, literal, twin,
                            val_plain, val_corr, world, time.monotonic() - t0,
                            reg_data.refusals + doe_data.refusals + val_plain.refusals + val_corr.refusals,
                            provenance=prov, checks=checks)
    finally:
        inst.close()
        world.close()
    (out / "summary.json").write_text(json.dumps(result.summary, indent=2))
    progress.note(f"wrote {out / 'summary.json'} and the twin in {out / 'model'}")
    return result


def sim_instruments(cfg: DemoConfig, inst: Instruments, world: SimWorld) -> tuple[Instrument, ...]:
    """The simulated instruments with the uncertainty their simulator configs state (no
    certificate: they are simulated). The drivers' own truth (e.g. the rig's scale error) is not
    a statement and is left out."""
    cell, scn = world.cell.cell, world.cell.scenario
    lt = cell.laser_tracker
    out = [
        Instrument("robot", f"simulated arm (scenario {world.scenario_name})", cfg.drivers.robot,
                   model="simulated (sim.plant)", uncertainty={
                       "kind": "standard", "k": None,
                       "text": f"controller TCP resolution {scn.tcp_resolution_m * 1e6:g} um; joint repeatability "
                               f"{scn.joint_noise_rad:.3g} rad (1 sigma)",
                       "terms": {"tcp_resolution": {"value": scn.tcp_resolution_m, "unit": "m"},
                                 "joint_repeatability": {"value": scn.joint_noise_rad, "unit": "rad"}}}),
        Instrument("tracker", "simulated laser tracker", cfg.drivers.tracker,
                   model="simulated (sim.instruments.SimLaserTracker)", uncertainty={
                       "kind": "standard", "k": None,
                       "text": f"u = {lt.u_const_m * 1e6:g} um + {lt.u_per_m * 1e6:g} um/m x L (standard "
                               "uncertainty at distance L, isotropic; paper Sect. 2.5)",
                       "terms": {"constant": {"value": lt.u_const_m, "unit": "m"},
                                 "per_length": {"value": lt.u_per_m, "unit": "m/m"}}})]
    rig = getattr(inst.camera, "cfg", None)
    sigma_px = getattr(getattr(rig, "processing", None), "centroid_sigma_px", None)
    if sigma_px is not None:
        out.append(Instrument("camera", "simulated multi-camera marker tracking rig (synthetic images + OpenCV)",
                              cfg.drivers.camera, model="simulated (sim.camera_rig, configs/cameras.yaml)",
                              uncertainty={"kind": "standard", "k": None,
                                           "text": f"centroid repeatability {sigma_px:g} px (1 sigma), propagated "
                                                   "to each reading's TCP covariance",
                                           "terms": {"centroid_sigma": {"value": sigma_px, "unit": "px"}}}))
    elif inst.camera is not None:
        u = cell.mvs.noise_m
        out.append(Instrument("camera", "simulated point-noise MVS stand-in", cfg.drivers.camera,
                              model="simulated (sim.instruments.SimPointMVS)",
                              uncertainty={"kind": "standard", "k": None,
                                           "text": f"u = {u * 1e6:g} um per axis (standard)",
                                           "terms": {"per_axis": {"value": u, "unit": "m"}}}))
    return tuple(out)


def demo_provenance(cfg: DemoConfig, config: Path, plan_file: Path, inst: Instruments, world: SimWorld,
                    phases: tuple[PhaseData, ...]) -> Provenance:
    """The demo's traceability record: the demo, scenario, cell and plan configs (and the camera
    rig's config with the image driver) hashed, the simulated instruments, the cell temperature."""
    base = config.parent
    files = [config, base / cfg.scenario, base / cfg.cell, plan_file]
    if getattr(inst.camera, "cfg", None) is not None:
        files.append(CONFIGS / "cameras.yaml")  # the image rig's default config (sim.camera_rig)
    temps = np.concatenate([np.asarray(p.temperature, dtype=float).ravel() for p in phases])
    return build_provenance(files, robot_name=f"simulated arm (scenario {world.scenario_name})",
                            instruments=sim_instruments(cfg, inst, world), temperature=temps)


OUTSIDE_BAND_M = (0.05, 0.15)  # the extrapolation check: 50-150 mm outside the DOE hull


def _coverage_checks(inst, twin, doe, speed_fracs, n, seed, world, progress) -> dict[str, CoverageCheck]:
    """Distinct random targets inside the DOE hull and in the band outside it, corrected and
    scored against the truth (a check only the simulator allows; the paper's 14 validation
    points are unchanged)."""
    if n == 0 or twin.volume is None:
        return {}
    rng = np.random.default_rng([seed, 11])
    pts = np.unique(doe.X[:, :3], axis=0)
    out = {}
    for name, band in (("inside", (-np.inf, 0.0)), ("outside", OUTSIDE_BAND_M)):
        # Spare targets: only those whose corrected command is reachable too, and of those the
        # first n the arm reaches from where it stands (the IK's branch depends on the path).
        targets = sample_targets(twin.volume, pts, 3 * n, band, world, rng)
        speeds = rng.choice(np.asarray(speed_fracs, dtype=float), 3 * n)
        cmds = np.array([twin.corrected_command(x, s * inst.max_speed) for x, s in zip(targets, speeds)])
        bad = {i for i, _ in world.unreachable(cmds)}
        keep = [i for i in range(len(targets)) if i not in bad][:2 * n]
        res = run_check(inst, twin, targets[keep], speeds[keep], progress, f"coverage check, {name} the DOE volume")
        if res.n < n:
            raise UnreachableError(f"coverage check {name}: only {res.n} of {len(keep)} corrected commands reached")
        out[name] = res.head(n)
    return out


def _mm(a) -> list[float]:
    return [round(float(v) * 1e3, 6) for v in np.asarray(a).ravel()]


def _summarise(plan_cfg, quick, fr, doe, r_lt, r_mvs_lt, budgets, literal, twin, val_plain, val_corr,
               world, elapsed, refusals, provenance: Provenance | None = None,
               checks: dict[str, CoverageCheck] | None = None) -> DemoResult:
    # True errors in GL (the frame the tracker realises): intended target vs where the arm went.
    def true_err(v):
        ok = np.all(np.isfinite(v.truth_lt), axis=1)
        return fr.T_rdk.apply(v.target[ok]) - fr.T_lt.apply(v.truth_lt[ok]), ok

    e_plain, _ = true_err(val_plain)
    e_corr, ok_corr = true_err(val_corr)
    rms_plain, rms_corr = rms3(e_plain), rms3(e_corr)

    b11 = budgets["eq11_tcp_c"]
    # The stated uncertainty of each corrected validation position (Eq. 11 at its command).
    U_tcp = np.array([twin.correct(c, v).U for c, v in zip(val_corr.target[ok_corr], val_corr.speed[ok_corr])])
    inside = np.abs(e_corr) <= U_tcp
    coverage_val = {ax: float(inside[:, k].mean()) for k, ax in enumerate(AXES)}
    checks = checks or {}
    chk = {k: c.summary() for k, c in checks.items()}
    u_ratio = (float(checks["outside"].U.mean() / checks["inside"].U.mean())
               if {"inside", "outside"} <= set(checks) else None)

    # Eq. 17 on every corrected validation measurement: (e_LT_hat - e_MVS) vs e_MVS-LT_hat.
    vc = val_corr
    okm = np.all(np.isfinite(vc.p_mvs), axis=1) & np.all(np.isfinite(vc.p_rdk), axis=1)
    cmd_gl = fr.T_rdk.apply(vc.p_rdk[okm])
    e_mvs = cmd_gl - fr.T_mvs.apply(vc.p_mvs[okm])
    X = np.column_stack([vc.p_rdk[okm], vc.speed[okm]])
    e_lt_hat = twin.e_lt.predict(X)
    e_ml_hat = twin.e_mvs_lt.predict(X)
    b14, b16 = budgets["eq14_e_lt_hat_minus_e_mvs"], budgets["eq16_e_mvs_lt_hat"]
    tt = unc.t_test(e_lt_hat - e_mvs, e_ml_hat, b14.combined(), b16.combined(),
                    b14.effective_dof(), b16.effective_dof())

    s_e_mvs = np.std(doe.e_mvs, axis=0, ddof=1)
    prec = unc.precision_figures(s_e_mvs, b16)
    prec_lit = unc.precision_figures(s_e_mvs, literal["eq16_e_mvs_lt_hat"])
    U_tcp_lit = literal["eq11_tcp_c"].expanded()

    def expanded(b):
        return {"U_mm": _mm(b.expanded()), "k": [round(float(k), 4) for k in b.coverage_factor()],
                "dof_eff": [float(d) if np.isfinite(d) else None for d in b.effective_dof()]}

    mvs_acc = None
    if doe.e_true is not None:
        # MVS against truth over the DOE, both in GL: e_true - e_MVS = truth - MVS measurement.
        dm = doe.e_true - doe.e_mvs
        mvs_acc = {"rms_3d_mm": round(rms3(dm) * MM_PER_M, 4),
                   "rms_per_axis_mm": _mm(np.sqrt(np.mean(dm ** 2, axis=0))),
                   "note": "MVS TCP (registered to GL) minus the true TCP, over the DOE positionings"}
    summary = {
        "scenario": world.scenario_name,
        "mvs_vs_truth": mvs_acc,
        "quick": quick,
        "seed": plan_cfg.seed,
        "precision_before_mm": round(float(prec["before_avg_mm"]), 4),
        "precision_after_mm": round(float(prec["after_avg_mm"]), 4),
        "improvement_pct": round(float(prec["improvement_pct"]), 2),
        "precision_per_axis": {"before_2s_e_mvs_doe_mm": _mm(2 * s_e_mvs),
                               "after_U_e_mvs_lt_hat_mm": _mm(b16.expanded())},
        "true_rms_uncorrected_mm": round(rms_plain * 1e3, 4),
        "true_rms_corrected_mm": round(rms_corr * 1e3, 4),
        "true_error_reduction_pct": round(100 * (1 - rms_corr / rms_plain), 2),
        "coverage_95": chk["inside"]["coverage_95"] if "inside" in chk else coverage_val,
        "coverage_95_outside": chk["outside"]["coverage_95"] if "outside" in chk else None,
        "u_ratio_outside_inside": u_ratio,
        "coverage_check": {
            "note": "distinct random targets commanded with the correction, true error (simulator) against the "
                    "per-position U(TCP_c) of Eq. 11; inside: the DOE's convex hull; outside: "
                    f"{OUTSIDE_BAND_M[0] * 1e3:.0f}-{OUTSIDE_BAND_M[1] * 1e3:.0f} mm beyond it",
            **chk, "validation": {"n": int(len(U_tcp)), "coverage_95": coverage_val,
                                  "mean_U_mm": _mm(U_tcp.mean(axis=0)) if len(U_tcp) else None}},
        "paper_literal_budget": {
            "note": "registration residual spread added as in the paper's Eqs. 13-16 (double counts, see README)",
            "precision_after_mm": round(float(prec_lit["after_avg_mm"]), 4),
            "improvement_pct": round(float(prec_lit["improvement_pct"]), 2),
            "U_tcp_c_mm": _mm(U_tcp_lit),
            "coverage_95": {ax: float(np.mean(np.abs(e_corr[:, k]) <= U_tcp_lit[k])) for k, ax in enumerate(AXES)}},
        "n_validation": int(ok_corr.sum()),
        "table2_registration_residuals": {k: mean_std_mm(v) for k, v in fr.residuals.items()},
        "reproducibility_mm": {"reprod_tcp": _mm(fr.reprod_tcp), "reprod_mvs": _mm(fr.reprod_mvs)},
        "table3_as_is": {"e_lt_doe": mean_std_mm(doe.e_lt), "e_mvs_doe": mean_std_mm(doe.e_mvs),
                         "e_mvs_lt_doe": mean_std_mm(doe.e_mvs_lt)},
        "table4_model_residuals_cv": {
            "note": "held-out residuals (grouped by target point); the budget uses the replicate means",
            "r_lt": mean_std_mm(r_lt), "r_mvs_lt": mean_std_mm(r_mvs_lt),
            "r_lt_replicate_means": mean_std_mm(cal.replicate_means(r_lt, doe.groups, doe.X[:, 3])),
            "r_mvs_lt_replicate_means": mean_std_mm(cal.replicate_means(r_mvs_lt, doe.groups, doe.X[:, 3]))},
        "expanded_uncertainty_95": {
            "eq18_tcp_c": expanded(b11), "eq19_e_lt_hat": expanded(budgets["eq13_e_lt_hat"]),
            "eq20_e_lt_hat_minus_e_mvs": expanded(b14), "eq21_e_mvs": expanded(budgets["eq15_e_mvs"]),
            "eq22_e_mvs_lt_hat": expanded(b16)},
        "budgets": {k: b.table(unit="mm") for k, b in budgets.items()},
        "t_test_eq17": {"n": int(len(tt.t)), "pass_fraction_all_axes": float(np.mean(tt.passed_all)),
                        "pass_fraction_per_axis": {ax: float(np.mean(tt.passed[:, k])) for k, ax in enumerate(AXES)}},
        "refusals": refusals[:50],
        "n_refusals": len(refusals),
        "elapsed_s": round(elapsed, 1),
        "units": "mm; errors e = commanded - measured, in the global frame GL",
        "provenance": provenance.to_dict() if provenance is not None else None,
    }
    arrays = {
        "reg_residuals": fr.residuals, "doe_X": doe.X, "e_lt": doe.e_lt, "e_mvs": doe.e_mvs,
        "e_mvs_lt": doe.e_mvs_lt, "r_lt": r_lt, "r_mvs_lt": r_mvs_lt, "e_true_doe": doe.e_true,
        "val_target": val_corr.target[ok_corr], "val_speed": val_corr.speed[ok_corr],
        "val_true_err_plain": e_plain, "val_true_err_corr": e_corr, "U_tcp_c": U_tcp,
        "U_e_mvs_lt_hat": b16.expanded(), "t_values": tt.t,
        "val_diff": e_lt_hat - e_mvs, "val_pred": e_ml_hat, "U_diff": b14.expanded(),
    }
    return DemoResult(summary, arrays)
