"""From raw phase data to a calibrated twin (the paper's Sects. 2.3-2.5).

1. Register LT, MVS and robot (RDK) frames to GL by the three-line method (Sect. 2.3).
2. Registration residuals (Eqs. 5-7, Table 2) and reproducibilities (Eq. 12).
3. DOE errors e_LT (Eq. 8), e_MVS (Eq. 9), e_MVS-LT (Eq. 10) in GL; Table 3.
4. Error maps e_LT_hat and e_MVS-LT_hat (hybrid models: the physical effects the user names + GP
   on (TCP, v); without effects, the paper's GPR); residuals r by cross-validation grouped by
   target point (a model cannot win by remembering a point), Table 4.
5. Uncertainty budgets Eqs. 11, 13-16, Eq. 11 per position and its split conformal factor on the
   held-out residuals (`conformal_scale`, `metrology.conformal`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.analysis.crossval import cross_validate, folds_of
from dt_runtime.frames import registration as reg
from dt_runtime.frames.volume import CalibratedVolume
from dt_runtime.measurements.phase import PhaseData
from dt_runtime.metrology import conformal
from dt_runtime.metrology import uncertainty as unc
from dt_runtime.metrology.conformal import ConformalScale
from dt_runtime.metrology.uncertainty import INF
from dt_runtime.models.effects import Inputs
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.twin.twin import PositionUncertainty, Twin


@dataclass
class Frames:
    """The three instruments registered to GL (Sect. 2.3), with what the budgets take from it.

    Attributes
    ----------
    T_rdk, T_lt, T_mvs : RigidTransform
        Robot (controller), laser tracker and camera (MVS) frame -> GL.
    residuals : dict
        Instrument name ('rdk', 'lt', 'mvs') -> (n, 3) m registration residuals (Eqs. 5-7).
    reprod_tcp, reprod_mvs : ndarray
        (3,) m, reproducibility of the TCP (tracker-measured) and of the camera (Eq. 12).
    reprod_tcp_dof, reprod_mvs_dof : float
        Their degrees of freedom.
    """

    T_rdk: reg.RigidTransform
    T_lt: reg.RigidTransform
    T_mvs: reg.RigidTransform
    residuals: dict  # name -> (n,3) m, Eqs. 5-7
    reprod_tcp: np.ndarray
    reprod_tcp_dof: float
    reprod_mvs: np.ndarray
    reprod_mvs_dof: float


def register(data: PhaseData) -> Frames:
    """Register robot, tracker and camera to GL by the three-line method and compute the
    reproducibilities of Eq. 12 from the replicated registration points.

    Parameters
    ----------
    data : PhaseData
        The registration phase (positions in m, with each row's `axis` and `distance`); rows
        where the tracker or the camera refused (NaN) are left out of their reproducibility.

    Returns
    -------
    Frames
    """
    p_gl = reg.gl_nominal(data.axis, data.distance)
    regs = {name: reg.register_instrument(getattr(data, f"p_{name}"), p_gl, "three_line",
                                          axes=data.axis, distances=data.distance)
            for name in ("rdk", "lt", "mvs")}
    T = {name: r.transform for name, r in regs.items()}
    res = {name: r.residuals for name, r in regs.items()}
    # Eq. 12: reproducibility from replicated positionings at the 12 registration points.
    ok_lt = np.all(np.isfinite(data.p_lt), axis=1)
    ok_mvs = np.all(np.isfinite(data.p_mvs), axis=1)
    r_tcp, dof_tcp = reg.reproducibility(T["lt"].apply(data.p_lt[ok_lt]), data.point_id[ok_lt])
    r_mvs, dof_mvs = reg.reproducibility(T["mvs"].apply(data.p_mvs[ok_mvs]), data.point_id[ok_mvs])
    return Frames(T["rdk"], T["lt"], T["mvs"], res, np.asarray(r_tcp), float(dof_tcp),
                  np.asarray(r_mvs), float(dof_mvs))


@dataclass
class DoeErrors:
    """The DOE phase's errors in GL (e = commanded - measured), on the rows both the tracker and
    the camera measured.

    Attributes
    ----------
    X : ndarray
        (n, 4): commanded TCP (robot frame, m) and speed (m/s).
    e_lt, e_mvs, e_mvs_lt : ndarray
        (n, 3) m, GL axes: e_LT (Eq. 8), e_MVS (Eq. 9) and e_MVS-LT = e_LT - e_MVS (Eq. 10).
    groups : ndarray
        (n,) target point id of each row (the cross-validation groups).
    e_true : ndarray or None
        (n, 3) m, the error against the simulator's truth (simulation only).
    inputs : Inputs
        What the effect terms may read on these rows (time order).
    """

    X: np.ndarray  # (n,4): commanded TCP robot frame (m) and speed (m/s)
    e_lt: np.ndarray  # (n,3) GL, m (Eq. 8)
    e_mvs: np.ndarray  # (n,3) (Eq. 9)
    e_mvs_lt: np.ndarray  # (n,3) (Eq. 10)
    groups: np.ndarray  # target point id
    e_true: np.ndarray | None  # (n,3) truth-based error in GL (simulation only)
    inputs: Inputs  # what the effect terms may read on these rows (time order)


def phase_inputs(data: PhaseData, rows: np.ndarray) -> Inputs:
    """The effect terms' inputs of a phase's rows: the controller's commanded TCP and joints,
    speed, and the temperature, payload and time where every row has them.

    Parameters
    ----------
    data : PhaseData
        The phase (SI units: m, rad, m/s, deg C, kg, s).
    rows : ndarray
        Boolean mask or indices of the rows to take.

    Returns
    -------
    Inputs
        A column (joints, temperature, payload, time) is None unless it is finite on every row.
    """

    def col(a: np.ndarray) -> np.ndarray | None:
        a = np.asarray(a, dtype=float)[rows]
        return a if a.size and np.all(np.isfinite(a)) else None

    return Inputs(commanded=data.p_rdk[rows], joints=col(data.q), speed=data.speed[rows],
                  temperature=col(data.temperature), payload=col(data.payload), t=col(data.t))


def doe_errors(data: PhaseData, fr: Frames) -> DoeErrors:
    """The DOE errors e_LT, e_MVS and e_MVS-LT in GL (Eqs. 8-10).

    Parameters
    ----------
    data : PhaseData
        The DOE phase (m, m/s); rows where the tracker or the camera refused are dropped.
    fr : Frames
        The registration (`register`).

    Returns
    -------
    DoeErrors
    """
    ok = np.all(np.isfinite(data.p_lt), axis=1) & np.all(np.isfinite(data.p_mvs), axis=1)
    cmd_gl = fr.T_rdk.apply(data.p_rdk[ok])
    e_lt = cmd_gl - fr.T_lt.apply(data.p_lt[ok])
    e_mvs = cmd_gl - fr.T_mvs.apply(data.p_mvs[ok])
    e_true = None
    if data.truth_lt is not None:
        e_true = cmd_gl - fr.T_lt.apply(data.truth_lt[ok])
    X = np.column_stack([data.p_rdk[ok], data.speed[ok]])
    return DoeErrors(X, e_lt, e_mvs, e_lt - e_mvs, data.point_id[ok], e_true, phase_inputs(data, ok))


def replicate_means(r: np.ndarray, groups: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Mean residual per (target point, speed): the model's error for the mean positioning.

    Eq. 11 adds the positioning reproducibility separately; residuals of single positionings
    would count that scatter twice.

    Parameters
    ----------
    r : ndarray
        (n, 3) residuals (or any per-row values to average).
    groups : ndarray
        (n,) target point id.
    speed : ndarray
        (n,) m/s (rounded to 1e-9 to group).

    Returns
    -------
    ndarray
        (m, 3): the mean per distinct (point, speed), in the order of `numpy.unique`.
    """
    keys = np.column_stack([groups, np.round(speed, 9)])
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    counts = np.bincount(inv)
    return np.column_stack([np.bincount(inv, weights=r[:, k]) / counts for k in range(3)])


@dataclass
class FittedMaps:
    """The fitted error maps with their held-out residuals (Table 4).

    Attributes
    ----------
    e_lt : HybridModel
        e_LT_hat(TCP, v, ...): the named effects + GP, fitted on the whole DOE.
    e_mvs_lt : HybridModel
        e_MVS-LT_hat(TCP, v): GP.
    r_lt, r_mvs_lt : ndarray
        (n, 3) m, held-out residuals of e_LT and e_MVS-LT (grouped by target point).
    s_lt : ndarray
        (n, 3) m, the fold models' standard uncertainty at each held-out row.
    """

    e_lt: HybridModel  # e_LT_hat(TCP, v, ...): the named effects + GP
    e_mvs_lt: HybridModel  # e_MVS-LT_hat(TCP, v): GP
    r_lt: np.ndarray  # (n,3) held-out residuals of e_LT (Table 4)
    r_mvs_lt: np.ndarray  # (n,3) held-out residuals of e_MVS-LT
    s_lt: np.ndarray  # (n,3) the fold models' standard uncertainty at each held-out row


def map_model(effects: tuple[str, ...] = (), seed: int = 0, robot=None, gp_inputs: str = "tcp_speed",
              gp_options=None, catalogue=None) -> HybridModel:
    """The e_LT map's configuration (unfitted): the named effects + GP; none: the paper's GPR.

    Parameters
    ----------
    effects : tuple of str
        Effect names (`models.effects`); empty: GP only.
    seed : int
        Seed of the GP optimiser's starts.
    robot : str, Path, Chain or None
        The robot reference the joint-space effects need (`models.hybrid.HybridModel`).
    gp_inputs : str
        What the GP reads: 'tcp_speed', 'tcp', 'joints' or 'none'.
    gp_options : GPOptions or None
        The GP's options (None: its defaults).
    catalogue : Catalogue or None
        The `effects.Catalogue` the names refer to (default `effects.default()`).

    Returns
    -------
    HybridModel
        Unfitted.
    """
    return HybridModel(tuple(effects), gp_inputs, seed=seed, robot=robot, gp_options=gp_options,
                       catalogue=catalogue)


def fit_models(doe: DoeErrors, folds: int, seed: int, lt_model: HybridModel | None = None) -> FittedMaps:
    """Fit e_LT (configuration `lt_model`, default the paper's GPR) and e_MVS-LT (GPR: the two
    instruments' difference, which the robot's effects do not enter) on the DOE, with their
    held-out residuals: each target point predicted by a map that never saw it, hyperparameters
    included (Table 4); for e_LT also the fold maps' stated std there, which calibrates the
    per-position uncertainty.

    Parameters
    ----------
    doe : DoeErrors
        The DOE errors (`doe_errors`).
    folds : int
        Number of cross-validation folds (grouped by target point).
    seed : int
        Seed of the fold split and of the GP optimisers.
    lt_model : HybridModel or None
        The e_LT map's configuration (`map_model`); None: the paper's GPR.

    Returns
    -------
    FittedMaps
    """
    cfg = lt_model if lt_model is not None else map_model(seed=seed)
    masks = folds_of(doe.groups, folds, seed)
    e_lt = cfg.unfitted().fit(doe.inputs, doe.e_lt)
    cv = cross_validate(cfg, doe.inputs, doe.e_lt, doe.groups, masks, return_std=True, hyper_per_fold=True)
    mvs = map_model(seed=seed)
    e_mvs_lt = mvs.unfitted().fit(doe.inputs, doe.e_mvs_lt)
    r_mvs_lt = cross_validate(mvs, doe.inputs, doe.e_mvs_lt, doe.groups, masks, hyper_per_fold=True).residual
    assert cv.std is not None  # return_std=True
    return FittedMaps(e_lt, e_mvs_lt, cv.residual, r_mvs_lt, cv.std)


def model_scale(r: np.ndarray, s: np.ndarray, groups: np.ndarray, speed: np.ndarray) -> tuple[np.ndarray, float]:
    """The calibration lambda of the model's stated standard deviation, per axis, and its dof.

    Over the held-out replicate means (point, speed), lambda^2 = mean((r - mean r)^2) / mean(s^2):
    the scale that makes the GP's latent std sigma(c) state, on average over the DOE, the
    held-out spread s(r_LT) that the global budget uses. At a new position lambda sigma(c) then
    varies as the GP's own uncertainty does: small among the DOE points, growing away from them
    (extrapolation). dof: the number of replicate means minus one (a variance ratio estimated
    from them).

    Parameters
    ----------
    r : ndarray
        (n, 3) m, held-out residuals of e_LT.
    s : ndarray
        (n, 3) m, the fold models' stated standard uncertainty at the same rows.
    groups : ndarray
        (n,) target point id.
    speed : ndarray
        (n,) m/s.

    Returns
    -------
    lam : ndarray
        (3,) lambda per axis (dimensionless; 0 on an axis where the stated std is 0).
    dof : float
    """
    rm = replicate_means(r, groups, speed)
    sm = replicate_means(s, groups, speed)
    ms = np.mean(sm ** 2, axis=0)
    lam = np.sqrt(np.mean((rm - rm.mean(axis=0)) ** 2, axis=0) / np.where(ms > 0, ms, np.inf))
    return lam, float(len(rm) - 1)


def metrology_inputs(fr: Frames, r_lt: np.ndarray, r_mvs_lt: np.ndarray, lt_distance_m: float,
                     resol_tcp: float = 1e-6, resol_mvs: float = 5e-6,
                     registration_term: str = "transform") -> unc.MetrologyInputs:
    """The per-axis statistics the budgets of Eqs. 11-16 take (`metrology.uncertainty`).

    Parameters
    ----------
    fr : Frames
        The registration: its residuals and reproducibilities.
    r_lt, r_mvs_lt : ndarray
        (n, 3) m, held-out residuals of e_LT and e_MVS-LT.
    lt_distance_m : float
        The tracker's distance to the work volume (m), for its calibration uncertainty.
    resol_tcp, resol_mvs : float
        Resolution of the robot's positioning and of the camera (m).
    registration_term : str
        'transform' (the fitted registration's uncertainty) or 'spread' (the residual spread, as
        the paper writes Eqs. 13-16): `MetrologyInputs.registration_term`.

    Returns
    -------
    MetrologyInputs
    """
    def stat(e):
        return np.mean(e, axis=0), np.std(e, axis=0, ddof=1), len(e)

    return unc.MetrologyInputs(
        reprod_tcp=fr.reprod_tcp, reprod_tcp_dof=fr.reprod_tcp_dof, resol_tcp=resol_tcp,
        reg_lt=stat(fr.residuals["lt"]), reg_mvs=stat(fr.residuals["mvs"]),
        u_lt=unc.lt_standard_uncertainty(lt_distance_m),
        res_lt=stat(r_lt), res_mvs_lt=stat(r_mvs_lt),
        reprod_mvs=fr.reprod_mvs, reprod_mvs_dof=fr.reprod_mvs_dof, resol_mvs=resol_mvs,
        registration_term=registration_term,
    )


def budgets(inp) -> dict:
    """The calibration's uncertainty budgets, Eqs. 11 and 13-16.

    Parameters
    ----------
    inp : MetrologyInputs
        From `metrology_inputs`.

    Returns
    -------
    dict
        twin.json's keys ('eq11_tcp_c', 'eq13_e_lt_hat', 'eq14_e_lt_hat_minus_e_mvs',
        'eq15_e_mvs', 'eq16_e_mvs_lt_hat') -> `Budget`.
    """
    return {
        "eq11_tcp_c": unc.budget_tcp_corrected(inp),
        "eq13_e_lt_hat": unc.budget_e_lt_hat(inp),
        "eq14_e_lt_hat_minus_e_mvs": unc.budget_elt_minus_emvs(inp),
        "eq15_e_mvs": unc.budget_e_mvs(inp),
        "eq16_e_mvs_lt_hat": unc.budget_e_mvs_lt_hat(inp),
    }


def extrapolation_scale(doe: DoeErrors, scale: np.ndarray, lt_model: HybridModel) -> tuple[np.ndarray, float]:
    """kappa per axis (m of error per m outside the DOE hull) and its dof: how the e_LT model's
    error grows beyond what its own standard deviation says when it extrapolates.

    Leave-a-face-out: for each of the six directions +-x, +-y, +-z, the outermost layer of DOE
    points is held out and predicted by a GP fitted on the rest; each held-out replicate mean
    lies at a distance d outside the hull of the rest. The squared residual beyond what
    lambda sigma states is regressed on d^2 through the origin:
    kappa^2 = sum max(0, r^2 - (lambda sigma)^2) / sum d^2. The twin then adds kappa d(c) for a
    command c at distance d(c) > 0 outside the calibrated hull.

    Parameters
    ----------
    doe : DoeErrors
        The DOE errors.
    scale : ndarray
        (3,) lambda per axis (`model_scale`).
    lt_model : HybridModel
        The e_LT map; refitted (unfitted copies) on each face's rest.

    Returns
    -------
    kappa : ndarray
        (3,) per axis, m of error per m outside the hull; zeros when no face could be held out.
    dof : float
        Held-out replicate means minus one; infinite when no face could be held out.
    """
    P = doe.X[:, :3]
    design = lt_model.design_matrix(doe.inputs)  # on all rows, in time order (approach direction)
    num, den, n = np.zeros(3), 0.0, 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            v = sign * P[:, axis]
            held = v >= v.max() - 1e-6
            if held.all():
                continue
            try:
                rest = CalibratedVolume.of_points(P[~held])
            except DataError:  # the rest is flat: no extrapolation distance to speak of
                continue
            m = lt_model.unfitted().fit(doe.inputs.subset(~held), doe.e_lt[~held], design=design.rows(~held))
            mu, sd = m.predict(doe.inputs.subset(held), return_std=True, design=design.rows(held))
            g, spd = doe.groups[held], doe.X[held, 3]
            rm = replicate_means(doe.e_lt[held] - mu, g, spd)
            sm = replicate_means(sd, g, spd)
            d = replicate_means(np.repeat(rest.distance(P[held])[:, None], 3, axis=1), g, spd)[:, 0]
            num += np.sum(np.maximum(rm ** 2 - (scale * sm) ** 2, 0.0), axis=0)
            den += float(np.sum(np.maximum(d, 0.0) ** 2))
            n += len(rm)
    if den <= 0 or n < 2:
        return np.zeros(3), INF
    return np.sqrt(num / den), float(n - 1)


def position_uncertainty(eq11: unc.Budget, doe: DoeErrors, maps: FittedMaps) -> PositionUncertainty:
    """Eq. 11 made per position: its components but the global model spread s(r_LT), which the
    calibrated model term lambda sigma_GP(c) replaces at each position, plus kappa d(c) outside
    the calibrated hull (`model_scale`, `extrapolation_scale`).

    Parameters
    ----------
    eq11 : Budget
        The global Eq. 11 budget (with its model term `metrology.uncertainty.MODEL_TERM`).
    doe : DoeErrors
        The DOE errors.
    maps : FittedMaps
        The fitted maps with their held-out residuals and stds.

    Returns
    -------
    PositionUncertainty
    """
    rest = tuple(c for c in eq11.components if c.label != unc.MODEL_TERM)
    assert len(rest) == len(eq11.components) - 1, f"Eq. 11 has no '{unc.MODEL_TERM}' component"
    scale, dof = model_scale(maps.r_lt, maps.s_lt, doe.groups, doe.X[:, 3])
    kappa, kdof = extrapolation_scale(doe, scale, maps.e_lt)
    return PositionUncertainty(unc.Budget("u(TCP_c) without the model", rest), scale, dof, kappa, kdof)


def conformal_scale(pu: PositionUncertainty, doe: DoeErrors, maps: FittedMaps) -> ConformalScale:
    """The split conformal factor of U(TCP_c) (`metrology.conformal`): each held-out DOE positioning's
    residual r_LT (by a fold map that never saw its target point) against the Eq. 11 U the twin
    states there (`PositionUncertainty.budget_at` with the fold map's sigma, inside the hull);
    the exchangeable unit is the target point (n = distinct DOE target points).

    lambda (`model_scale`) is estimated from the same held-out residuals: one parameter per axis
    from n points, an O(1/n) reuse that the finite-sample guarantee does not account for.

    Parameters
    ----------
    pu : PositionUncertainty
        Eq. 11 per position (`position_uncertainty`).
    doe : DoeErrors
        The DOE errors (their target point ids).
    maps : FittedMaps
        The held-out residuals r_lt and the fold maps' std s_lt.

    Returns
    -------
    ConformalScale
    """
    U = np.array([pu.budget_at(s, 0.0).expanded() for s in maps.s_lt]).reshape(-1, 3)
    return conformal.calibrate(maps.r_lt, U, doe.groups)


def make_twin(fr: Frames, e_lt, e_mvs_lt, b: dict, instruments: dict | None = None,
              volume: CalibratedVolume | None = None, position_u: PositionUncertainty | None = None,
              scale: ConformalScale | None = None) -> Twin:
    """The twin from its registration, fitted maps and budgets.

    Parameters
    ----------
    fr : Frames
        The registration.
    e_lt, e_mvs_lt : HybridModel
        The fitted error maps.
    b : dict
        twin.json's uncertainty key -> `Budget` (`budgets`); each is stated as u, dof, U and k
        per axis (m).
    instruments : dict or None
        The drivers it was calibrated with (e.g. the camera), recorded in twin.json.
    volume : CalibratedVolume or None
        The DOE's hull (where the maps interpolate).
    position_u : PositionUncertainty or None
        Eq. 11 per position (`position_uncertainty`).
    scale : ConformalScale or None
        The held-out conformal factor of U(TCP_c) (`conformal_scale`); None: factor 1.

    Returns
    -------
    Twin

    Raises
    ------
    ModelError
        A budget's stated figures are not finite and >= 0 per axis (`TwinUncertainty`), or the
        maps need a robot config that cannot be read.
    """
    u = {}
    for key, bud in b.items():
        u[key] = {"u": bud.combined(), "dof": bud.effective_dof(), "U": bud.expanded(), "k": bud.coverage_factor()}
    return Twin(fr.T_rdk, fr.T_lt, fr.T_mvs, e_lt, e_mvs_lt, u, dict(instruments or {}), volume, position_u,
                conformal=scale if scale is not None else ConformalScale())
