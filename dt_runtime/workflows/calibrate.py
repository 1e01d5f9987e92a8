"""A twin from a campaign's measurements (`dt calibrate`; `dt demo` runs the same code on the
files its simulated campaign wrote).

Registration (Sect. 2.3, Eqs. 5-7, 12), DOE errors (Eqs. 8-10), the error maps (the effects the
user names + GP; none: the paper's GPR) with held-out residuals (Table 4), the GUM budgets
(Eqs. 11, 13-16), the per-position uncertainty and the calibrated volume; optionally a
validation phase measured without correction: the map's prediction against the tracker at
points it never saw, the coverage of the per-position U there and the Eq. 17 t-test.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from dt_kernel.config import Frozen
from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.analysis import validity
from dt_runtime.common.progress import Progress
from dt_runtime.frames.volume import CalibratedVolume
from dt_runtime.measurements.phase import PhaseData
from dt_runtime.metrology import uncertainty as unc
from dt_runtime.metrology.stats import mean_std_mm, rms3
from dt_runtime.models import effects as fx
from dt_runtime.models.effects import Inputs
from dt_runtime.models.hybrid import GP_INPUTS, HybridModel
from dt_runtime.twin import calibration as cal
from dt_runtime.twin.twin import Twin


class CalibrationOptions(Frozen):
    """How the maps are fitted and the volume drawn (the demo config and `dt calibrate` flags)."""

    cv_folds: int = Field(5, ge=2, le=50)
    # The calibrated volume: the DOE's convex hull widened by this margin (m); beyond it a
    # correction is flagged as extrapolation.
    volume_margin_m: float = Field(0.025, ge=0.0, le=0.5)
    effects: tuple[str, ...] = ()  # the e_LT map's physical effect terms (none: the paper's GPR)
    gp_inputs: str = "tcp_speed"
    seed: int = 0

    @field_validator("effects")
    @classmethod
    def _known(cls, v: tuple[str, ...], info: ValidationInfo) -> tuple[str, ...]:
        # The call's catalogue (`model_validate(..., context={"catalogue": cat})`, e.g. with
        # --effects-file's declarations), else the default one.
        cat = (info.context or {}).get("catalogue") or fx.default()
        cat.check_names(v)
        return v

    @field_validator("gp_inputs")
    @classmethod
    def _gp(cls, v: str) -> str:
        if v not in GP_INPUTS:
            raise ValueError(f"one of {', '.join(GP_INPUTS)}")
        return v


@dataclass
class Campaign:
    """A campaign's phases (SI), as run through the drivers or read from its files."""

    registration: PhaseData
    doe: PhaseData
    validation: PhaseData | None = None


@dataclass
class Calibrated:
    """A calibration's result (`calibrate`): the twin and what it was built from.

    Attributes
    ----------
    twin : Twin
        The calibrated twin.
    frames : Frames
        The registration (Sect. 2.3).
    doe : DoeErrors
        The DOE errors (Eqs. 8-10).
    maps : FittedMaps
        The fitted maps with their held-out residuals (Table 4).
    budgets : dict
        twin.json's key -> `Budget`, Eqs. 11 and 13-16 (registration as a fitted transform: the
        default).
    literal : dict
        The same with the registration spread added as the paper writes it (double counts).
    """

    twin: Twin
    frames: cal.Frames
    doe: cal.DoeErrors
    maps: cal.FittedMaps
    budgets: dict  # Eqs. 11, 13-16 (registration as a transform: the default)
    literal: dict  # the same with the registration spread added as in the paper (double counts)


def calibrate(campaign: Campaign, options: CalibrationOptions, robot=None, instruments: dict | None = None,
              progress: Progress | None = None, lt_model: HybridModel | None = None,
              catalogue: fx.Catalogue | None = None) -> Calibrated:
    """Register, fit the maps, compute the budgets and the per-position uncertainty: the twin.

    robot: the robot config (path) the joint-space effects and the deployment's inverse
    kinematics use; lt_model: the e_LT map's configuration (e.g. a `dt fit` model's), default
    `options.effects` + GP; catalogue: the effects `options.effects` refer to (e.g. with
    --effects-file's declarations, which the twin's map keeps), default `effects.default()`.

    Parameters
    ----------
    campaign : Campaign
        The phases (SI); the validation phase is not used here (`validation`).
    options : CalibrationOptions
        Folds, volume margin, effects, GP inputs and seed.
    robot : str or None
        The robot reference (`frames.robots`) the joint-space effects read.
    instruments : dict or None
        The drivers that measured (role -> driver name), recorded in the twin.
    progress : Progress or None
        Where progress notes go (None: nowhere).
    lt_model : HybridModel or None
        The e_LT map's configuration; None: `options.effects` + GP.
    catalogue : Catalogue or None
        The effects `options.effects` refer to.

    Returns
    -------
    Calibrated

    Raises
    ------
    DataError
        The phases cannot be registered or fitted (e.g. too few points, a flat DOE).
    """
    progress = progress or Progress(enabled=False)
    frames = cal.register(campaign.registration)
    doe = cal.doe_errors(campaign.doe, frames)
    seed = options.seed
    cfg = lt_model.unfitted() if lt_model is not None else cal.map_model(
        options.effects, seed, robot, options.gp_inputs, catalogue=catalogue)
    what = f"effects {', '.join(cfg.effects)} + GP" if cfg.effects else "GPR"
    progress.note(f"fitting the error maps e_LT ({what}) and e_MVS-LT (GPR), grouped cross-validation")
    maps = cal.fit_models(doe, options.cv_folds, seed, cfg)
    p_lt = campaign.doe.p_lt
    lt_dist = float(np.median(np.linalg.norm(p_lt[np.all(np.isfinite(p_lt), 1)], axis=1)))
    speed = doe.X[:, 3]
    inp = cal.metrology_inputs(frames, cal.replicate_means(maps.r_lt, doe.groups, speed),
                               cal.replicate_means(maps.r_mvs_lt, doe.groups, speed), lt_dist)
    budgets = cal.budgets(inp)
    literal = cal.budgets(dataclasses.replace(inp, registration_term="spread"))
    progress.note("per-position uncertainty: held-out calibration of the map's std, leave-a-face-out extrapolation")
    pu = cal.position_uncertainty(budgets["eq11_tcp_c"], doe, maps)
    twin = cal.make_twin(frames, maps.e_lt, maps.e_mvs_lt, budgets, instruments,
                         CalibratedVolume.of_points(doe.X[:, :3], options.volume_margin_m), pu,
                         cal.conformal_scale(pu, doe, maps))
    return Calibrated(twin, frames, doe, maps, budgets, literal)


def _mm(a) -> list[float]:
    return [round(float(v) * MM_PER_M, 6) for v in np.asarray(a).ravel()]


def expanded(b: unc.Budget) -> dict:
    """A budget's expanded uncertainty for a summary.

    Parameters
    ----------
    b : Budget
        The budget (m).

    Returns
    -------
    dict
        `U_mm` (per axis, mm, 95 %), `k` (coverage factors) and `dof_eff` (None where infinite).
    """
    return {"U_mm": _mm(b.expanded()), "k": [round(float(k), 4) for k in b.coverage_factor()],
            "dof_eff": [float(d) if np.isfinite(d) else None for d in b.effective_dof()]}


def figures(c: Calibrated) -> dict:
    """The calibration's figures (mm): the paper's Sect. 3.3 precision, Tables 2-4, the budgets
    and Eqs. 18-22, the maps' effect parameters. What a summary of `dt calibrate` and of
    `dt demo` share.

    Parameters
    ----------
    c : Calibrated
        The calibration.

    Returns
    -------
    dict
        JSON-ready; keys as in docs/cli.md (`dt demo`'s and `dt calibrate`'s summary).
    """
    fr, doe, b = c.frames, c.doe, c.budgets
    s_e_mvs = np.std(doe.e_mvs, axis=0, ddof=1)
    b16 = b["eq16_e_mvs_lt_hat"]
    prec = unc.precision_figures(s_e_mvs, b16)
    prec_lit = unc.precision_figures(s_e_mvs, c.literal["eq16_e_mvs_lt_hat"])
    g, v = doe.groups, doe.X[:, 3]
    e_lt = c.twin.e_lt
    return {
        "precision_before_mm": round(float(prec["before_avg_mm"]), 4),
        "precision_after_mm": round(float(prec["after_avg_mm"]), 4),
        "improvement_pct": round(float(prec["improvement_pct"]), 2),
        "precision_per_axis": {"before_2s_e_mvs_doe_mm": _mm(2 * s_e_mvs),
                               "after_U_e_mvs_lt_hat_mm": _mm(b16.expanded())},
        "maps": {"e_lt": {"effects": list(e_lt.effects), "gp_inputs": e_lt.gp_inputs, "parameters": e_lt.parameters(),
                          "base_parameters": e_lt.base_parameters()},
                 "e_mvs_lt": {"effects": list(c.twin.e_mvs_lt.effects), "gp_inputs": c.twin.e_mvs_lt.gp_inputs}},
        "paper_literal_budget": {
            "note": "registration residual spread added as in the paper's Eqs. 13-16 (double counts, see docs/demo.md)",
            "precision_after_mm": round(float(prec_lit["after_avg_mm"]), 4),
            "improvement_pct": round(float(prec_lit["improvement_pct"]), 2),
            "U_tcp_c_mm": _mm(c.literal["eq11_tcp_c"].expanded())},
        "n_doe": int(len(doe.X)),
        "table2_registration_residuals": {k: mean_std_mm(r) for k, r in fr.residuals.items()},
        "reproducibility_mm": {"reprod_tcp": _mm(fr.reprod_tcp), "reprod_mvs": _mm(fr.reprod_mvs)},
        "table3_as_is": {"e_lt_doe": mean_std_mm(doe.e_lt), "e_mvs_doe": mean_std_mm(doe.e_mvs),
                         "e_mvs_lt_doe": mean_std_mm(doe.e_mvs_lt)},
        "table4_model_residuals_cv": {
            "note": "held-out residuals (grouped by target point); the budget uses the replicate means",
            "r_lt": mean_std_mm(c.maps.r_lt), "r_mvs_lt": mean_std_mm(c.maps.r_mvs_lt),
            "r_lt_replicate_means": mean_std_mm(cal.replicate_means(c.maps.r_lt, g, v)),
            "r_mvs_lt_replicate_means": mean_std_mm(cal.replicate_means(c.maps.r_mvs_lt, g, v))},
        "expanded_uncertainty_95": {
            "eq18_tcp_c": expanded(b["eq11_tcp_c"]), "eq19_e_lt_hat": expanded(b["eq13_e_lt_hat"]),
            "eq20_e_lt_hat_minus_e_mvs": expanded(b["eq14_e_lt_hat_minus_e_mvs"]),
            "eq21_e_mvs": expanded(b["eq15_e_mvs"]), "eq22_e_mvs_lt_hat": expanded(b16)},
        "budgets": {k: bud.table(unit="mm") for k, bud in b.items()},
        "uncertainty_calibration": c.twin.conformal.to_dict(),
    }


def arrays(c: Calibrated) -> dict:
    """The raw arrays (SI) the report's figures of the calibration draw.

    Parameters
    ----------
    c : Calibrated
        The calibration.

    Returns
    -------
    dict
        Name -> array (m; `doe_X` also m/s) or dict of arrays (`reg_residuals`).
    """
    d = c.doe
    return {"reg_residuals": c.frames.residuals, "doe_X": d.X, "e_lt": d.e_lt, "e_mvs": d.e_mvs,
            "e_mvs_lt": d.e_mvs_lt, "r_lt": c.maps.r_lt, "r_mvs_lt": c.maps.r_mvs_lt, "e_true_doe": d.e_true,
            "U_e_mvs_lt_hat": c.budgets["eq16_e_mvs_lt_hat"].expanded()}


@dataclass
class Eq17:
    """Eq. 17 on a phase's rows (`eq17`).

    Attributes
    ----------
    test : TTest
        t, dof, p-values and pass flags per row and axis.
    diff : ndarray
        (n, 3) m, e_LT_hat - e_MVS, GL axes.
    pred : ndarray
        (n, 3) m, e_MVS-LT_hat, GL axes.
    """

    test: unc.TTest
    diff: np.ndarray  # e_LT_hat - e_MVS, GL, m
    pred: np.ndarray  # e_MVS-LT_hat, GL, m


def eq17(c: Calibrated, phase: PhaseData) -> Eq17:
    """Eq. 17 on every row of a phase the MVS measured: (e_LT_hat - e_MVS) against
    e_MVS-LT_hat, with the stated Eqs. 14 and 16 uncertainties.

    Parameters
    ----------
    c : Calibrated
        The calibration.
    phase : PhaseData
        The phase (m, m/s); rows without a camera or controller position are left out.

    Returns
    -------
    Eq17
    """
    ok = np.all(np.isfinite(phase.p_mvs), axis=1) & np.all(np.isfinite(phase.p_rdk), axis=1)
    fr = c.frames
    e_mvs = fr.T_rdk.apply(phase.p_rdk[ok]) - fr.T_mvs.apply(phase.p_mvs[ok])
    inp = cal.phase_inputs(phase, ok)
    e_lt_hat = c.twin.e_lt.predict(inp)
    e_ml_hat = c.twin.e_mvs_lt.predict(inp)
    b14, b16 = c.budgets["eq14_e_lt_hat_minus_e_mvs"], c.budgets["eq16_e_mvs_lt_hat"]
    tt = unc.t_test(e_lt_hat - e_mvs, e_ml_hat, b14.combined(), b16.combined(),
                    b14.effective_dof(), b16.effective_dof())
    return Eq17(tt, e_lt_hat - e_mvs, e_ml_hat)


def eq17_summary(t: Eq17) -> dict:
    """Eq. 17's pass fractions for a summary.

    Parameters
    ----------
    t : Eq17
        The test (`eq17`).

    Returns
    -------
    dict
        `n`, `pass_fraction_all_axes` and `pass_fraction_per_axis` ({x, y, z}); fractions None
        when no row was tested.
    """
    tt = t.test
    return {"n": int(len(tt.t)), "pass_fraction_all_axes": float(np.mean(tt.passed_all)) if len(tt.t) else None,
            "pass_fraction_per_axis": {ax: float(np.mean(tt.passed[:, k])) if len(tt.t) else None
                                       for k, ax in enumerate(AXES)}}


@dataclass
class Validation:
    """A validation phase measured without correction, against the twin: the coverage sample
    (e_LT - e_LT_hat at each positioning against its U(TCP_c)) and Eq. 17 on the same phase."""

    sample: validity.Sample
    e_lt: np.ndarray  # (n,3) m, the tracker-measured error of the uncorrected positionings, GL
    eq17: Eq17

    def summary(self) -> dict:
        """The summary's `validation`: the tracker's error at points the maps never saw, what is
        left after subtracting the prediction (the error a corrected command would keep), its
        coverage by the per-position U(TCP_c) of Eq. 11, and the Eq. 17 t-test."""
        e, r, U = self.e_lt, self.sample.error, self.sample.U
        n = len(r)
        inside = np.abs(r) <= U
        return {
            "n": n,
            "note": "tracker-measured error e_LT of uncorrected validation positionings, and e_LT - e_LT_hat: the "
                    "error a corrected command would keep (plus the positioning reproducibility)",
            "rms_e_lt_mm": round(rms3(e) * MM_PER_M, 4) if n else None,
            "rms_after_map_mm": round(rms3(r) * MM_PER_M, 4) if n else None,
            "reduction_pct": round(100 * (1 - rms3(r) / rms3(e)), 2) if n and rms3(e) > 0 else None,
            "coverage_95": {ax: float(inside[:, k].mean()) if n else None for k, ax in enumerate(AXES)},
            "mean_U_mm": _mm(U.mean(axis=0)) if n else None,
            "t_test_eq17": eq17_summary(self.eq17),
        }


def validation(c: Calibrated, phase: PhaseData) -> Validation:
    """The twin against a validation phase measured without correction (`Validation`).

    Parameters
    ----------
    c : Calibrated
        The calibration.
    phase : PhaseData
        The validation phase (m, m/s); rows without a tracker or controller position are left out.

    Returns
    -------
    Validation
    """
    fr, twin = c.frames, c.twin
    ok = np.all(np.isfinite(phase.p_lt), axis=1) & np.all(np.isfinite(phase.p_rdk), axis=1)
    e = fr.T_rdk.apply(phase.p_rdk[ok]) - fr.T_lt.apply(phase.p_lt[ok])
    inp = cal.phase_inputs(phase, ok)
    pred, s = twin.e_lt.predict(inp, return_std=True)

    def U_at(p: np.ndarray, v: float, si: np.ndarray) -> np.ndarray:
        return twin.stated_U(twin.tcp_budget(p, v, sigma=si))

    U = np.array([U_at(p, v, si) for p, v, si in zip(phase.p_rdk[ok], phase.speed[ok], s)]).reshape(-1, 3)
    cond = Inputs(commanded=phase.p_rdk[ok], joints=phase.q[ok], t=phase.t[ok], temperature=phase.temperature[ok])
    sample = validity.Sample("validation", f"the {int(ok.sum())} validation positionings (uncorrected commands)",
                             "errors the laser tracker measured less the map's prediction (e_LT - e_LT_hat)",
                             e - pred, U, cond)
    return Validation(sample, e, eq17(c, phase))


def stated(block: dict, c: Calibrated) -> dict:
    """A validity block with the U its coverage checks used and the guarantee that U carries.

    Parameters
    ----------
    block : dict
        From `analysis.validity.assess`.
    c : Calibrated
        The calibration (its twin's conformal scale).

    Returns
    -------
    dict
        The block with `stated_U` (the U in words), `guarantee` and `sample_size` (held-out target
        points the conformal factor was calibrated on; 0 for none).
    """
    cs = c.twin.conformal
    block["stated_U"] = ("U(TCP_c) = max(1, c) x Eq. 11's U per position, c the split conformal factor "
                         f"{[round(float(f), 4) for f in cs.raw]} (applied {[round(float(f), 4) for f in cs.factor]})"
                         if cs.method != "none" else "U(TCP_c) = Eq. 11's U per position (no conformal factor)")
    block["guarantee"] = cs.guarantee
    block["sample_size"] = cs.n
    return block


def validity_of(c: Calibrated, v: Validation | None, campaign: str | None) -> dict:
    """The `validity` block of a calibration (`analysis.validity`): the validation phase's coverage and
    Eq. 17 on it; without a validation phase, nothing tests the stated uncertainty and it says so.

    Parameters
    ----------
    c : Calibrated
        The calibration.
    v : Validation or None
        The validation (`validation`), if the campaign has a validation phase.
    campaign : str or None
        The campaign directory, for the advice.

    Returns
    -------
    dict
        The block `analysis.validity.assess` returns.
    """
    if v is None:
        return stated(validity.assess([], unchecked="the campaign has no validation phase, so nothing tests the stated "
                                             "U(TCP_c): measure one (uncorrected, at points the DOE did not visit) "
                                             "and give it with --validation (docs/campaign-files.md)"), c)
    rates = validity.Eq17Rates(v.eq17.test.passed, c.budgets["eq14_e_lt_hat_minus_e_mvs"].expanded())
    return stated(validity.assess([v.sample], c.doe.inputs, ("validation", rates), campaign), c)
