"""Typed results of `fit`, `diagnose` and `compare`. Each `to_dict()` gives the JSON object of
the command line (docs/cli.md: contract keys marked), in millimetres, JSON-ready (no numpy, no NaN).

    r = diagnose(...)
    r.ranking[0].effect, r.ranking[0].p_value        # typed
    dumps(r)                                         # the `dt diagnose --json` object
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from dt_runtime.common.jsonsafe import jsonable
from dt_runtime.common.provenance import Provenance


# --------------------------------------------------------------------------- fit
@dataclass
class FitResult:
    """A trained and saved model: where, on what, its parameters, its base parameters (the
    identifiable combinations) and (with CV) held-out RMS."""

    out: str
    n: int
    effects: list[str]
    gp_inputs: str
    robot: str | None
    fit_seconds: float
    train_rmse_mm: float
    parameters: list[dict]  # value +/- u per effect parameter (HybridModel.parameters)
    source: dict = field(default_factory=dict)  # the data's facts (load_data's info, without n)
    heldout_rmse_mm: float | None = None  # with cv_folds > 1
    as_is_rmse_mm: float | None = None
    provenance: Provenance | None = None  # the traceability record saved with the model
    base_parameters: dict | None = None  # what the data determine (HybridModel.base_parameters)

    def to_dict(self) -> dict:
        """The result as the JSON object of `dt fit --json`."""
        d: dict[str, Any] = {"out": self.out, "n": self.n, "effects": self.effects, "gp_inputs": self.gp_inputs,
                             "robot": self.robot, "fit_seconds": self.fit_seconds,
                             "train_rmse_mm": self.train_rmse_mm, "parameters": self.parameters,
                             "base_parameters": self.base_parameters, **self.source}
        if self.heldout_rmse_mm is not None:
            d |= {"heldout_rmse_mm": self.heldout_rmse_mm, "as_is_rmse_mm": self.as_is_rmse_mm}
        d["provenance"] = self.provenance
        return jsonable(d)


# --------------------------------------------------------------------------- diagnose
@dataclass
class Gain:
    """What one candidate change (an effect added, or the GP on other inputs) does to the
    starting model's held-out 3D RMS, and whether it is significant (one-sided p < alpha)."""

    kind: str  # "effect" or "gp_inputs": the JSON key naming the candidate
    candidate: str
    explained_fraction: float  # 1 - (after / before)^2: share of held-out residual variance
    p_value: float
    rmse_before_mm: float
    rmse_after_mm: float
    significant: bool
    # The same change on the scheme deployment brings (analysis.validation: 'regions', 'time' or
    # 'sessions'), when computed: the held-out 3D RMS before and after.
    deploy_kind: str | None = None
    deploy_rmse_before_mm: float | None = None
    deploy_rmse_after_mm: float | None = None
    factor: str | None = None  # what the residual follows when this effect is missing (Effect.factor)

    @property
    def deploys(self) -> bool | None:
        """Whether the change also lowers the deployment figure (None: not computed)."""
        if self.deploy_rmse_after_mm is None or self.deploy_rmse_before_mm is None:
            return None
        return self.deploy_rmse_after_mm < self.deploy_rmse_before_mm

    def to_dict(self) -> dict:
        """The gain as a JSON-ready dict, keyed by its kind."""
        d = {self.kind: self.candidate, "explained_fraction": self.explained_fraction,
             "p_value": self.p_value, "rmse_before_mm": self.rmse_before_mm,
             "rmse_after_mm": self.rmse_after_mm, "significant": self.significant}
        if self.factor is not None:
            d["factor"] = self.factor
        if self.deploy_kind is not None:
            d |= {"deploy_kind": self.deploy_kind, "deploy_rmse_before_mm": self.deploy_rmse_before_mm,
                  "deploy_rmse_after_mm": self.deploy_rmse_after_mm}
        return jsonable(d)


@dataclass
class DiagnoseResult:
    """Candidate effects (and GP inputs) ranked, best first; the verdict's words are the reports'
    (dt_runtime.reports.verdicts.verdict)."""

    base_effects: list[str]
    gp_inputs: str
    n: int
    n_groups: int
    folds: int
    rmse_base_mm: float
    noise_floor_mm: float | None
    ranking: list[Gain]
    gp_inputs_ranking: list[Gain]
    # Candidates not tested: {'candidate', 'reason': 'columns' (the data lack what it reads) or
    # 'confounded' (analysis.confounding: its factor follows the pose, or does not vary), ...}.
    not_testable: list[dict]
    source: dict = field(default_factory=dict)  # the data's facts (load_data's info, without n)
    provenance: Provenance | None = None  # software, data file hashes, robot, instruments
    base_group_mse: Any = None  # the starting model's held-out mean square per group (m^2; not in the JSON)
    base_residual: Any = None  # the starting model's held-out residual per row (m; not in the JSON)
    columns: list = field(default_factory=list)  # column_check: what the held-out residual follows
    validation: dict = field(default_factory=dict)  # the schemes: significance (points), deployment, time
    model_columns: list = field(default_factory=list)  # the columns the starting model reads

    @property
    def top(self) -> Gain | None:
        """The best-ranked candidate, or None."""
        return self.ranking[0] if self.ranking else None

    def to_dict(self) -> dict:
        """The result as the JSON object of `dt diagnose --json`."""
        return jsonable({"base_effects": self.base_effects, "gp_inputs": self.gp_inputs, "n": self.n,
                         "n_groups": self.n_groups, "folds": self.folds, "rmse_base_mm": self.rmse_base_mm,
                         "noise_floor_mm": self.noise_floor_mm, "ranking": self.ranking,
                         "gp_inputs_ranking": self.gp_inputs_ranking, "not_testable": self.not_testable,
                         "columns": self.columns, "model_columns": self.model_columns,
                         "validation": self.validation, **self.source,
                         "provenance": self.provenance})


@dataclass
class AutoResult:
    """`dt diagnose --auto`: the steps (each with its held-out figures by point and on the
    deployment scheme), what was added and why, what could not be tested, the sessions, whether
    the final model may be deployed, and where it was saved."""

    start: str
    start_config: dict
    steps: list  # analysis.selection.Step
    added: list[str]
    final_config: dict
    effects: list[str]
    gp_inputs: str
    session_terms: list[str]
    final_rmse_mm: float  # held out by point
    final_deploy_rmse_mm: float  # held out on the deployment scheme
    deploy_kind: str  # 'regions' or 'sessions'
    as_is_rmse_mm: float
    noise_floor_mm: float | None
    floor_ratio: float | None
    stop_reason: str
    not_testable: list[dict]
    alpha: float
    min_explained: float
    n: int
    folds: int
    validation: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)
    provenance: Provenance | None = None
    columns: list = field(default_factory=list)  # column_check on the final model's held-out residual
    model_columns: list = field(default_factory=list)  # the columns the final model reads
    sessions: list = field(default_factory=list)  # each session held out: final (and start) vs as is
    session_terms_tested: list = field(default_factory=list)
    session_term_values: list = field(default_factory=list)
    deploy: dict = field(default_factory=dict)  # {'ok': bool, 'by': scheme}
    reference_session: str | None = None  # the session the nuisance terms are measured against
    model_out: str | None = None
    # The diagnosis's cross-validations (analysis.evaluation.Evaluator; not in the JSON): a caller
    # scoring the same configurations on the same data reuses them.
    evaluator: Any = None
    # Every row's held-out residual (by point, the steps' figure) of the first and the final model,
    # with the rows' points, sessions, speeds and joints (not in the JSON): the arrays of
    # reports.residuals, written beside the model by `dt diagnose --auto --out` (residuals.csv).
    heldout_rows: dict | None = None

    def to_dict(self) -> dict:
        """The result as the JSON object of `dt diagnose --auto --json`."""
        d = {k: v for k, v in self.__dict__.items() if k not in ("steps", "source", "evaluator", "heldout_rows")}
        return jsonable(d | {"steps": [s.to_dict() for s in self.steps]} | self.source)


# --------------------------------------------------------------------------- compare
@dataclass
class ModelScore:
    """One column of a comparison ("as is" or a model): figures of merit in mm, the Eq. 17
    failures, the residual per factor cell and the worst cells."""

    name: str
    kind: str  # "as is" or "model"
    n: int
    metrics: dict  # rmse_mm, rmse_U95_mm, mae_mm, max_mm, max_row, per_axis (compare.metrics)
    failures: dict | None  # None without any measurement uncertainty
    breakdown: dict
    worst_cells: list[dict]
    description: str
    model: dict | None = None  # effects, gp_inputs, effect_residual_rms_mm, parameters (models only)
    sessions: list[dict] | None = None  # data of several sessions: each one's figures (compare._by_session)

    @property
    def rmse_mm(self) -> float:
        """3D RMS of the residuals, mm."""
        return self.metrics["rmse_mm"]

    def to_dict(self) -> dict:
        """The column as a JSON-ready dict."""
        return jsonable({"name": self.name, "kind": self.kind, "n": self.n, **self.metrics,
                         "failures": self.failures, "breakdown": self.breakdown,
                         "worst_cells": self.worst_cells, "description": self.description, **(self.model or {}),
                         **({"sessions": self.sessions} if self.sessions is not None else {})})


@dataclass
class CompareResult:
    """"as is" and every model, side by side; the primary model (the last) also at the top level
    of the JSON, so `n`, `rmse_mm`, `mae_mm`, `per_axis`, `failures` are top-level keys."""

    models: list[ModelScore]
    dataset: str
    noise_floor_mm: float | None
    heldout: dict | None  # the CV method and folds, None for the models as saved
    t_test: dict  # what Eq. 17 used: equation, u_model, u_meas_source
    factors: dict[str, list[str]]  # factor -> its cells in order
    units: str = "mm; e = commanded - measured (Eq. 8); residual r = e - e_hat"
    provenance: Provenance | None = None  # software, data and model file hashes, instruments
    in_sample: list[str] = field(default_factory=list)  # models trained on these very data (figures not held out)
    validity: dict = field(default_factory=dict)  # the primary model's U95 against these data (analysis.validity)
    conformal: dict | None = None  # with cv_folds > 1: the held-out conformal factor of the primary model's U95

    @property
    def primary(self) -> ModelScore:
        """The primary model: the last one given."""
        return self.models[-1]

    def to_dict(self) -> dict:
        """The result as the JSON object of `dt compare --json` (the primary model's figures on top)."""
        top = {k: v for k, v in self.primary.to_dict().items() if k not in ("name", "kind")}
        return jsonable({**top, "primary": self.primary.name, "dataset": self.dataset,
                         "noise_floor_mm": self.noise_floor_mm, "heldout": self.heldout, "t_test": self.t_test,
                         "factors": self.factors, "models": self.models, "units": self.units,
                         "in_sample": self.in_sample, "validity": self.validity, "provenance": self.provenance,
                         **({"conformal": self.conformal} if self.conformal is not None else {})})
