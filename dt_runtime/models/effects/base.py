"""What every effect term shares: the inputs it may read, the regressor block it returns, and
the `Effect` base class that declares an effect once (name, columns, kinematic chain, the factor
the diagnose verdict names) and checks its inputs before building.

An effect builds, for every row, a 3 x p regressor block A with e = commanded - measured
= A theta. Joint-space effects act through the TCP Jacobian J of the nominal kinematics: the
arm reaches fk(q + dq) ~ fk(q) + J dq, so a joint deviation dq contributes e = -J dq.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar, cast

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.frames.kinematics import Chain


@dataclass(frozen=True)
class Inputs:
    """What the effect terms may use; SI units, rows in time order."""

    commanded: np.ndarray  # (n,3) m
    joints: np.ndarray | None = None  # (n,dof) rad
    speed: np.ndarray | None = None  # (n,) m/s
    temperature: np.ndarray | None = None  # (n,) deg C
    payload: np.ndarray | None = None  # (n,) kg
    t: np.ndarray | None = None  # (n,) s
    # The time origin of the drift term (s): a fitted model's first training row, so that
    # predictions on later rows continue its clock; None: the first row's t.
    t_origin: float | None = None
    # The structure's temperature (n,) deg C when known already (a deployed twin's running
    # thermal state, `MapPredictor`): the thermal effect then does not lag the logged one itself.
    structure_temperature: np.ndarray | None = None
    # The data's own numeric columns by name (`Dataset.extra`: humidity, a fixture's
    # temperature), which the user's declared effects read.
    extra: dict[str, np.ndarray] | None = None

    @property
    def n(self) -> int:
        """Number of rows."""
        return len(self.commanded)

    @classmethod
    def of(cls, ds) -> Inputs:
        """The columns of a `dt_runtime.measurements.dataset.Dataset` the effect terms may use.

        Parameters
        ----------
        ds : Dataset
            The measurements.

        Returns
        -------
        Inputs
        """
        return cls(**{f.name: getattr(ds, f.name) for f in fields(cls)
                      if f.name not in ("t_origin", "structure_temperature", "extra")},
                   extra=dict(getattr(ds, "extra", {}) or {}) or None)

    def subset(self, mask) -> Inputs:
        """The rows where `mask` selects (every array column, and `extra`).

        Parameters
        ----------
        mask : array-like
            Boolean mask or indices of rows.

        Returns
        -------
        Inputs
        """
        return replace(self, **{f.name: v[mask] for f in fields(self)
                                if isinstance(v := getattr(self, f.name), np.ndarray)},
                       extra=None if self.extra is None else {k: v[mask] for k, v in self.extra.items()})

    def get(self, name: str) -> np.ndarray | None:
        """A column by name: a field of Inputs, else one of the data's own (`extra`), else None.

        Parameters
        ----------
        name : str
            The column's name.

        Returns
        -------
        ndarray or None
        """
        if name in _FIELDS:
            return getattr(self, name)
        return None if self.extra is None else self.extra.get(name)

    def has(self, *columns: str) -> bool:
        """Whether every named column is there.

        Parameters
        ----------
        *columns : str
            Column names (fields of Inputs or the data's own).

        Returns
        -------
        bool
        """
        return all(self.get(c) is not None for c in columns)

    def column(self, name: str) -> np.ndarray:
        """An optional column that must be there (an effect declared it: `Effect.build` checks).

        Parameters
        ----------
        name : str
            The column's name.

        Returns
        -------
        ndarray

        Raises
        ------
        DataError
            When the data have no such column.
        """
        v = self.get(name)
        if v is None:
            raise DataError(f"the data has no column {name!r}")
        return v


_FIELDS = frozenset(f.name for f in fields(Inputs))
# A factor an effect varies with, by the Inputs column that carries it.
_FACTOR_OF = {"time": "t", "temperature": "temperature", "speed": "speed", "payload": "payload"}


def as_inputs(X) -> Inputs:
    """The effect terms' inputs of X: an `effects.Inputs`, a measurement `Dataset`, or an
    (n, 3) array of commanded TCP positions (m).

    Parameters
    ----------
    X : Inputs, Dataset or ndarray
        The data.

    Returns
    -------
    Inputs
    """
    if isinstance(X, Inputs):
        return X
    if hasattr(X, "commanded"):
        return Inputs.of(X)
    P = np.asarray(X, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise DataError(f"X must be a Dataset, effects.Inputs or an (n, 3) array of commanded TCP "
                        f"positions, got shape {P.shape}")
    return Inputs(commanded=P)


@dataclass(frozen=True)
class Block:
    """One effect's regressors: A (n, 3, p) with e = A theta, each parameter's name and unit, how it
    is reported, and whether physics wants its parameters >= 0.
    """
    effect: str
    A: np.ndarray  # (n, 3, p)
    names: tuple[str, ...]
    units: tuple[str, ...]
    # Reported quantity per parameter: identity, or 1/x (compliance -> stiffness).
    report: str = "identity"
    # Physics' sign: every parameter of the block >= 0 (a backlash width, a compliance), else free.
    nonnegative: bool = False


def approach(x: np.ndarray, per_column: bool = False) -> np.ndarray:
    """Direction of approach of each row from the previous row (first row: from the second). A
    row that did not move (a repeated reading of the same pose) keeps the direction of the last
    move: the arm still rests where that move left it. per_column: each column on its own (a joint
    that did not move while others did keeps its own last direction, as the plant's play does).

    Parameters
    ----------
    x : ndarray
        (n, k) positions or joint angles, rows in time order.
    per_column : bool, optional
        Each column on its own.

    Returns
    -------
    ndarray
        (n, k) the differences to the previous row.
    """
    x = np.asarray(x, dtype=float)
    d = np.zeros_like(x)
    if len(x) < 2:
        return d
    d[1:] = x[1:] - x[:-1]
    d[0] = d[1]
    return carry_forward(d, np.abs(d) <= 1e-12 * np.maximum(1.0, np.abs(x)), per_column)


def carry_forward(d: np.ndarray, still: np.ndarray, per_column: bool = False) -> np.ndarray:
    """`d` with every `still` entry replaced by the last entry before it that was not still (its
    column's first such entry before any); per_column False: a row is still only when all of it is.

    Parameters
    ----------
    d : ndarray
        (n, k).
    still : ndarray
        (n, k) bool.
    per_column : bool, optional
        Each column on its own.

    Returns
    -------
    ndarray
        (n, k).
    """
    if not per_column:
        still = np.broadcast_to(np.all(still, axis=1, keepdims=True), d.shape)
    if not still.any():
        return d
    rows = np.arange(len(d))[:, None]
    last = np.maximum.accumulate(np.where(still, -1, rows), axis=0)  # the last row that moved
    first = np.where(still.all(axis=0), 0, np.argmax(~still, axis=0))  # before any move: the first move
    idx = np.where(last < 0, first[None, :], last)
    return np.take_along_axis(d, idx, axis=0)


class Effect:
    """One physical effect term. A subclass declares, once:

    name: the contract name (docs/effects.md) (the simulator's scenario uses the same).
    columns: the `Inputs` columns its regressors read.
    needs_chain: whether it acts through the robot's kinematic chain (joint-space effects).
    factor: what the residual follows when the effect is missing (the diagnose verdict).
    hyper: the grid of each nonlinear parameter (keyword of `regressors`), which the fit
    chooses by profile likelihood (`models.hyper`), e.g. the thermal lag; hyper_units their
    units, hyper_columns the columns their estimate needs (the lag: the time t); hyper_choices
    the labels of a parameter whose grid values are alternatives (the backlash's move model).
    and implements `regressors(inp, chain, **hyper) -> Block`."""

    name: ClassVar[str]
    columns: ClassVar[tuple[str, ...]]
    needs_chain: ClassVar[bool] = True
    # True for an effect that reads the kinematic chain when the model has one, but does not
    # need it (the thermal effect per link, Chain.thermal_links).
    uses_chain: ClassVar[bool] = False
    factor: ClassVar[str]
    hyper: ClassVar[dict[str, np.ndarray]] = {}
    hyper_units: ClassVar[dict[str, str]] = {}
    hyper_columns: ClassVar[tuple[str, ...]] = ()  # the columns without which they cannot be estimated
    # Nonlinear parameters that are a choice between alternatives (grid value i -> label i), e.g.
    # how the backlash reads the approach: chosen by profile likelihood, no interval.
    hyper_choices: ClassVar[dict[str, tuple[str, ...]]] = {}
    # What the effect varies with beyond the pose (`drives`); None: from its columns.
    varies_with: ClassVar[tuple[str, ...] | None] = None

    def drives(self) -> tuple[str, ...]:
        """What, beyond the pose, the effect varies with (the diagnosis checks that the campaign
        varies it independently of the pose before testing the effect): 'time', 'temperature',
        'speed', 'payload', 'direction' (of approach) or a column of the data. Default: from the
        columns it reads (the joints are the pose)."""
        if self.varies_with is not None:
            return self.varies_with
        named = {v: k for k, v in _FACTOR_OF.items()}
        return tuple(named.get(c, c) for c in self.columns if c not in ("joints", "commanded"))

    def reads(self, chain: Chain | None) -> tuple[str, ...]:
        """The columns its regressors read with this chain (default: `columns`).

        Parameters
        ----------
        chain : Chain or None
            The robot's kinematic chain.

        Returns
        -------
        tuple of str
        """
        return self.columns

    def allowed(self, inp: Inputs, chain: Chain | None) -> bool:
        """Whether the data's columns (and the kinematic chain, if needed) allow this effect.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain or None
            The robot's kinematic chain.

        Returns
        -------
        bool
        """
        return inp.has(*self.reads(chain)) and (chain is not None or not self.needs_chain)

    def build(self, inp: Inputs, chain: Chain | None, hyper: dict[str, float] | None = None) -> Block:
        """The regressor block, after checking that the inputs allow it; `hyper`: values of the
        nonlinear parameters (default: each one's `regressors` default).

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain or None
            The robot's kinematic chain.
        hyper : dict, optional
            Values of the nonlinear parameters.

        Returns
        -------
        Block

        Raises
        ------
        DataError
            When a column, the chain or a named nonlinear parameter is missing or unknown.
        """
        missing = [c for c in self.reads(chain) if inp.get(c) is None]
        if missing:
            raise DataError(f"effect '{self.name}' needs the column(s) {', '.join(missing)}, "
                            f"which the data does not have")
        if self.needs_chain and chain is None:
            raise DataError(f"effect '{self.name}' needs the robot's kinematic model (parameter robot)")
        unknown = set(hyper or {}) - set(self.hyper)
        if unknown:
            raise DataError(f"effect '{self.name}' has no nonlinear parameter {', '.join(sorted(unknown))}")
        return self.regressors(inp, cast(Chain, chain), **(hyper or {}))  # None only where needs_chain is False

    def regressors(self, inp: Inputs, chain: Chain) -> Block:  # pragma: no cover - abstract
        """The block; `build` has checked the columns (and the chain, where needed).

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain
            The robot's kinematic chain.

        Returns
        -------
        Block
        """
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<effect {self.name}>"
