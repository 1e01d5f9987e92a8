"""The calibrated twin: frames, error maps and uncertainty, with the correction law.

Sign convention (docs/measurement-table.md, Eq. 8): e = commanded - measured. The twin's estimate of where the
robot really is: TCP_hat = TCP_cmd - e_hat(TCP_cmd, v). To reach a target the corrected command
solves c - e_hat(c, v) = target by fixed-point iteration, starting at c = target + e_hat(target, v).
Maps predict errors in the GL axes; the robot frame is rotated by R_RDK^GL (nearly identity).

The error maps e_LT and e_MVS-LT are hybrid models (`models.hybrid.HybridModel`: physical effect
terms + GP); the paper's GP-only map is the case without effects. A map with effect terms reads
the command's `Conditions` (joint angles, temperature, payload, time, direction of approach:
`twin.conditions`); the paper's map reads only the command and its speed.

The stated uncertainties are read through `Twin.uncertainty` (`TwinUncertainty`: one
`StatedUncertainty` per equation, Eqs. 11 and 13-16), never by string keys; `Twin.u` is the same
data as twin.json holds it (format_version 1: `u.eq11_tcp_c.{u, dof, U, k}`, ...). The U(TCP_c) a
corrected position states is Eq. 11's times the held-out conformal factor (`Twin.conformal`,
twin.json's `uncertainty_calibration`; `metrology.conformal`).
"""
from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from dt_kernel.errors import ModelError, TwinError
from dt_runtime.common.jsonsafe import jsonable
from dt_runtime.common.provenance import Provenance
from dt_runtime.frames.registration import RigidTransform
from dt_runtime.frames.volume import CalibratedVolume
from dt_runtime.metrology.conformal import ConformalScale
from dt_runtime.metrology.uncertainty import Budget, Component, budget_tcp_corrected_at
from dt_runtime.models.hybrid import HybridModel, load_map
from dt_runtime.models.modelio import read_meta
from dt_runtime.twin.conditions import Conditions, command_inputs

# 2: the maps are hybrid model directories (TWIN/e_lt/, TWIN/e_mvs_lt/); 1 (read too): GP-only
# maps saved as TWIN/e_lt.json + .npz.
FORMAT_VERSION = 2
READS = (1, 2)


@dataclass(frozen=True)
class StatedUncertainty:
    """One equation's stated uncertainty, per axis (x, y, z), in metres."""

    u: np.ndarray  # combined standard uncertainty
    dof: np.ndarray  # effective degrees of freedom (Welch-Satterthwaite; inf allowed)
    k: np.ndarray  # coverage factor for 95 %
    U: np.ndarray  # expanded uncertainty, 95 %

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str) -> StatedUncertainty:
        """One equation's entry of twin.json's "u" object, checked.

        Parameters
        ----------
        m : Mapping
            Keys u, dof, k and U, each three values (m; dof and k dimensionless).
        where : str
            Where the entry is, for the error message.

        Returns
        -------
        StatedUncertainty

        Raises
        ------
        ModelError
            A key is missing, a value is not one number per axis, or not finite and >= 0 (dof
            must be > 0 and may be infinite).
        """
        try:
            vals = {f.name: np.asarray(m[f.name], dtype=float) for f in fields(cls)}
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"{where}: needs u, dof, k and U per axis ({exc!r})") from exc
        bad = [k for k, v in vals.items() if v.shape != (3,)]
        if bad:
            raise ModelError(f"{where}: {bad[0]} has shape {vals[bad[0]].shape}, expected one value per axis (3,)")
        # A stated uncertainty of inf or NaN would make every command "inside" its U: refused.
        # Only the degrees of freedom may be infinite (GUM G.6.6).
        bad = [k for k, v in vals.items() if not (np.all(v >= 0) if k == "dof" else np.all(np.isfinite(v) & (v >= 0)))]
        if bad or not np.all(vals["dof"] > 0):
            k = bad[0] if bad else "dof"
            raise ModelError(f"{where}: {k} is {vals[k].tolist()}, expected finite values >= 0 per axis "
                             "(dof > 0, infinity allowed)")
        return cls(**vals)


@dataclass(frozen=True)
class TwinUncertainty:
    """The twin's stated uncertainties (GUM budgets of calibration), per equation of the paper."""

    tcp_c: StatedUncertainty  # Eq. 11: the corrected TCP
    e_lt_hat: StatedUncertainty  # Eq. 13: the predicted LT error
    e_lt_hat_minus_e_mvs: StatedUncertainty  # Eq. 14: e_LT_hat - e_MVS (the t-test difference)
    e_mvs: StatedUncertainty  # Eq. 15: the MVS error
    e_mvs_lt_hat: StatedUncertainty  # Eq. 16: the predicted e_MVS-LT

    # field -> key in twin.json's "u" object (format_version 1)
    KEYS: ClassVar[dict[str, str]] = {"tcp_c": "eq11_tcp_c", "e_lt_hat": "eq13_e_lt_hat",
            "e_lt_hat_minus_e_mvs": "eq14_e_lt_hat_minus_e_mvs", "e_mvs": "eq15_e_mvs",
            "e_mvs_lt_hat": "eq16_e_mvs_lt_hat"}

    @classmethod
    def from_mapping(cls, u: Mapping[str, Any], where: str = "twin") -> TwinUncertainty:
        """From twin.json's "u" object (or the dict calibration builds).

        Parameters
        ----------
        u : Mapping
            Key (`KEYS`' values, e.g. 'eq11_tcp_c') -> the entry `StatedUncertainty.from_mapping` reads.
        where : str
            Where the object is, for the error message.

        Returns
        -------
        TwinUncertainty

        Raises
        ------
        ModelError
            Naming a missing or malformed entry.
        """
        missing = [k for k in cls.KEYS.values() if k not in u]
        if missing:
            raise ModelError(f"{where}: uncertainty '{missing[0]}' missing; a twin states {sorted(cls.KEYS.values())}")
        return cls(**{f: StatedUncertainty.from_mapping(u[k], f"{where}: u.{k}") for f, k in cls.KEYS.items()})


@dataclass(frozen=True)
class PositionUncertainty:
    """What Eq. 11 needs at any corrected position: the position-independent components, the
    calibration of the e_LT model's own standard deviation (lambda, `calibration.model_scale`)
    and its growth outside the calibrated hull (kappa, `calibration.extrapolation_scale`)."""

    rest: Budget  # Eq. 11 without the global model spread s(r_LT)
    model_scale: np.ndarray  # (3,) lambda per GL axis
    model_dof: float
    extrapolation_scale: np.ndarray  # (3,) kappa per GL axis, m of error per m outside the hull
    extrapolation_dof: float

    def budget_at(self, sigma_gp: np.ndarray, distance_m: float) -> Budget:
        """Eq. 11 where the GP states sigma_gp and the command lies distance_m outside the hull.

        Parameters
        ----------
        sigma_gp : ndarray
            (3,) m, the e_LT map's standard uncertainty at the command (GL axes).
        distance_m : float
            Signed distance of the command to the DOE hull (m); <= 0 (inside) adds no
            extrapolation term.

        Returns
        -------
        Budget
            The labelled Eq. 11 budget at the position.
        """
        return budget_tcp_corrected_at(self.rest, self.model_scale * np.asarray(sigma_gp), self.model_dof,
                                       self.extrapolation_scale * max(float(distance_m), 0.0),
                                       self.extrapolation_dof)

    def to_dict(self) -> dict[str, Any]:
        """JSON form, twin.json's `position_uncertainty` (an infinite dof is written as null)."""
        return {"rest": [c.to_dict() for c in self.rest.components], "model_scale": self.model_scale.tolist(),
                "model_dof": self.model_dof, "extrapolation_scale": self.extrapolation_scale.tolist(),
                "extrapolation_dof": self.extrapolation_dof if np.isfinite(self.extrapolation_dof) else None}

    @classmethod
    def from_dict(cls, d: Any, where: str) -> PositionUncertainty:
        """What `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            twin.json's `position_uncertainty` object.
        where : str
            Where it is, for the error message.

        Returns
        -------
        PositionUncertainty

        Raises
        ------
        ModelError
            A key is missing or malformed, a scale is not one value per axis, or there are no
            components.
        """
        try:
            comps = tuple(Component.from_dict(c) for c in d["rest"])
            scale = np.asarray(d["model_scale"], dtype=float)
            dof = float(d["model_dof"])
            kappa = np.asarray(d["extrapolation_scale"], dtype=float)
            kdof = float("inf") if d["extrapolation_dof"] is None else float(d["extrapolation_dof"])
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ModelError(f"{where}: position_uncertainty needs rest, model_scale, model_dof, "
                             f"extrapolation_scale, extrapolation_dof ({exc!r})") from exc
        if scale.shape != (3,) or kappa.shape != (3,) or not comps:
            raise ModelError(f"{where}: position_uncertainty: scales {scale.shape}, {kappa.shape} or no components")
        return cls(Budget("u(TCP_c) without the model", comps), scale, dof, kappa, kdof)


@dataclass(frozen=True)
class Correction:
    """A corrected command with the uncertainty of the position it reaches."""

    target: np.ndarray  # (3,) m, robot frame
    command: np.ndarray  # (3,) m, robot frame: solves c - e_hat(c, v) = target
    U: np.ndarray  # (3,) m, expanded uncertainty (95 %) of the corrected TCP, per GL axis (conformal factor x budget's)
    inside: bool  # the command lies in the calibrated volume (hull of the DOE plus its margin)
    distance_m: float  # signed distance of the command to the DOE hull (< 0 inside), NaN if unknown
    budget: Budget | None  # the labelled Eq. 11 (GUM) budget at this position (None for an old twin)


@dataclass
class Twin:
    """The calibrated twin: the frames, the error maps e_LT_hat and e_MVS-LT_hat and the stated
    uncertainties, with the correction law (`correct`). Saved and loaded as a directory
    (twin.json + the maps' directories; docs/cli.md, `dt calibrate`).

    Parameters
    ----------
    T_rdk, T_lt, T_mvs : RigidTransform
        Robot, laser tracker and camera (MVS) frame -> GL.
    e_lt : HybridModel
        e_LT_hat(TCP robot frame m, v m/s, conditions) -> GL axes, m.
    e_mvs_lt : HybridModel
        e_MVS-LT_hat(TCP, v, conditions) -> GL axes, m.
    u : dict
        The stated uncertainties as twin.json holds them (`TwinUncertainty.KEYS`' values ->
        u, dof, k, U per axis); read them through `uncertainty`.
    instruments : dict
        The drivers it was calibrated with, e.g. the camera.
    volume : CalibratedVolume or None
        Where the maps interpolate (the DOE hull); None: not recorded.
    position_u : PositionUncertainty or None
        Eq. 11 per position; None: only the global `uncertainty.tcp_c` is stated.
    provenance : Provenance or None
        The traceability record (`common.provenance`).
    conformal : ConformalScale
        The held-out calibration of U(TCP_c) (`metrology.conformal`): every corrected position's U is
        its factor times Eq. 11's; an older twin has none (factor 1).

    Raises
    ------
    ModelError
        A stated uncertainty is missing or malformed, or the maps read joint angles and their
        robot config cannot be read.
    """

    T_rdk: RigidTransform  # robot frame -> GL
    T_lt: RigidTransform  # tracker frame -> GL
    T_mvs: RigidTransform  # MVS frame -> GL
    e_lt: HybridModel  # e_LT_hat(TCP robot frame m, v m/s, conditions) -> GL axes, m
    e_mvs_lt: HybridModel  # e_MVS-LT_hat(TCP, v, conditions)
    u: dict  # stated uncertainties as twin.json holds them; read them through `uncertainty`
    instruments: dict = field(default_factory=dict)  # drivers it was calibrated with, e.g. camera
    volume: CalibratedVolume | None = None  # where the maps interpolate (None: an older twin)
    position_u: PositionUncertainty | None = None  # Eq. 11 per position (None: an older twin)
    provenance: Provenance | None = None  # traceability record (dt_runtime.common.provenance)
    conformal: ConformalScale = field(default_factory=ConformalScale)  # U(TCP_c) = factor x Eq. 11's U
    uncertainty: TwinUncertainty = field(init=False, repr=False)

    def __post_init__(self):
        self.uncertainty = TwinUncertainty.from_mapping(self.u)
        self._p_lt = self.e_lt.predictor()
        self._p_mvs_lt = self.e_mvs_lt.predictor()
        self._Rt = self.T_rdk.R.T  # GL axes -> robot axes
        self._chain = None
        if "joints" in self.needs:  # the deployment's inverse kinematics: the robot config must be there
            try:
                self._chain = self.e_lt.chain()
            except (TwinError, OSError) as exc:
                raise ModelError(f"the twin's e_LT map ({', '.join(self.e_lt.effects)}) needs its robot config "
                                 f"{self.e_lt.robot}, which cannot be read: {exc}") from exc

    @property
    def needs(self) -> tuple[str, ...]:
        """The conditions the maps read beside the command and its speed (`twin.conditions`)."""
        return tuple(dict.fromkeys(n for p in (self._p_lt, self._p_mvs_lt) for n in p.needs if n != "speed"))

    def _lt(self, c: np.ndarray, v: float, cond: Conditions | None, q_seed=None):
        """e_LT_hat at c in GL axes with its std, and c's joint angles (when the map reads them)."""
        if self._p_lt.plain:
            m, s = self._p_lt.gp_only(np.array([c[0], c[1], c[2], v]))
            return m, s, None
        inp, q = command_inputs(c, v, self._p_lt.needs, cond, self._chain, q_seed)
        m, s = self._p_lt(inp)
        return m, s, q

    def e_lt_hat(self, c: np.ndarray, v: float, cond: Conditions | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Predicted LT error at command c (robot frame): mean (robot axes, m) and standard
        uncertainty (GL axes, m).

        Parameters
        ----------
        c : ndarray
            (3,) m, the command (robot frame).
        v : float
            Speed, m/s.
        cond : Conditions or None
            What the maps read beside the command (`needs`).

        Returns
        -------
        mean : ndarray
            (3,) m, robot axes.
        std : ndarray
            (3,) m, GL axes.

        Raises
        ------
        DataError
            A condition the map needs is not given (`conditions.command_inputs`).
        """
        m, s, _ = self._lt(np.asarray(c, dtype=float), v, cond)
        return self._Rt @ m, s

    def e_mvs_lt_hat(self, c: np.ndarray, v: float, cond: Conditions | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Predicted e_MVS-LT at command c, GL axes, m.

        Parameters
        ----------
        c : ndarray
            (3,) m, the command (robot frame).
        v : float
            Speed, m/s.
        cond : Conditions or None
            What the maps read beside the command (`needs`).

        Returns
        -------
        mean, std : ndarray
            (3,) m each, GL axes.

        Raises
        ------
        DataError
            A condition the map needs is not given (`conditions.command_inputs`).
        """
        if self._p_mvs_lt.plain:
            return self._p_mvs_lt.gp_only(np.array([c[0], c[1], c[2], v]))
        chain = self._chain or (self.e_mvs_lt.chain() if "joints" in self._p_mvs_lt.needs else None)
        return self._p_mvs_lt(command_inputs(c, v, self._p_mvs_lt.needs, cond, chain)[0])

    def predicted_means(self, c: np.ndarray, v: float, cond: Conditions | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The means of `e_lt_hat` (robot axes) and `e_mvs_lt_hat` (GL axes) at command c, without
        their std: what Eq. 17 reads (`twin.monitor`), the same numbers.

        Parameters
        ----------
        c : ndarray
            (3,) m, the command (robot frame).
        v : float
            Speed, m/s.
        cond : Conditions or None
            What the maps read beside the command (`needs`).

        Returns
        -------
        e_lt, e_mvs_lt : ndarray
            (3,) m each.
        """
        c = np.asarray(c, dtype=float)
        if self._p_lt.plain and self._p_mvs_lt.plain:
            x = np.array([c[0], c[1], c[2], v])
            return self._Rt @ self._p_lt.gp_mean(x), self._p_mvs_lt.gp_mean(x)
        return self.e_lt_hat(c, v, cond)[0], self.e_mvs_lt_hat(c, v, cond)[0]

    @functools.cached_property
    def corrector(self):
        """The twin's correction law (`twin.corrector.Corrector`), built on first use; it shares
        this twin's e_LT predictor (a thermal map's structure temperature is carried across
        `correct`, `corrected_command` and `e_lt_hat`)."""
        from dt_runtime.twin.corrector import Corrector  # it builds on this module

        return Corrector(self, predictor=self._p_lt)

    def corrected_command(self, target: np.ndarray, v: float, cond: Conditions | None = None) -> np.ndarray:
        """The command that reaches `target` (m, robot frame) at speed v (m/s): `correct`'s command.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        v : float
            Speed, m/s.
        cond : Conditions or None
            What the maps read beside the command (`needs`).

        Returns
        -------
        ndarray
            (3,) m, robot frame.
        """
        return self.corrector.correct(target, v, cond).command

    def distance(self, c: np.ndarray) -> float:
        """Signed distance (m) of command c to the DOE hull (< 0 inside).

        Parameters
        ----------
        c : ndarray
            (3,) m, the command (robot frame).

        Returns
        -------
        float
            NaN for a twin without a calibrated volume.
        """
        return float(self.volume.distance(np.asarray(c, dtype=float))[0]) if self.volume is not None else float("nan")

    def tcp_budget(self, c: np.ndarray, v: float, distance_m: float | None = None,
                   cond: Conditions | None = None, sigma: np.ndarray | None = None) -> Budget | None:
        """Eq. 11 at command c (robot frame, m) and speed v: labelled components, the e_LT
        map's term from its standard uncertainty at c (sigma, when the caller has it), and its
        growth outside the calibrated hull (distance_m: c's `distance`, when the caller has it).
        None for a twin without `position_u` (then only the global `uncertainty.tcp_c` is known).

        Parameters
        ----------
        c : ndarray
            (3,) m, the command (robot frame).
        v : float
            Speed, m/s.
        distance_m : float or None
            c's signed distance to the hull (m); None: computed.
        cond : Conditions or None
            What the maps read beside the command (`needs`).
        sigma : ndarray or None
            (3,) m, the e_LT map's standard uncertainty at c; None: predicted.

        Returns
        -------
        Budget or None
        """
        if self.position_u is None:
            return None
        c = np.asarray(c, dtype=float)
        d = self.distance(c) if distance_m is None else distance_m
        s = self.e_lt_hat(c, v, cond)[1] if sigma is None else sigma
        return self.position_u.budget_at(s, d if np.isfinite(d) else 0.0)

    def stated_U(self, budget: Budget | None) -> np.ndarray:
        """The U(TCP_c) the twin states for an Eq. 11 budget: the conformal factor (`conformal`)
        times the budget's expanded uncertainty (the global Eq. 11 U when there is no budget).

        Parameters
        ----------
        budget : Budget or None
            Eq. 11 at a position (`tcp_budget`).

        Returns
        -------
        ndarray
            (3,) m, per GL axis.
        """
        U = budget.expanded() if budget is not None else self.uncertainty.tcp_c.U
        return self.conformal.factor * U

    def correct(self, target: np.ndarray, v: float, cond: Conditions | None = None) -> Correction:
        """The corrected command for a target, the expanded uncertainty (95 %) of the position it
        reaches with its labelled Eq. 11 budget, and whether the command lies in the calibrated
        volume: the one correction law (`corrector`).

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        v : float
            Speed, m/s.
        cond : Conditions or None
            What the maps read beside the command (`needs`).

        Returns
        -------
        Correction
        """
        sp = self.corrector.correct(target, v, cond)
        return sp.correction(target, self.corrector.budget(sp))

    # --- persistence: JSON + NPZ, no pickle ------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        """Write the twin: `directory`/twin.json (frames, stated uncertainties, volume, Eq. 11
        per position, provenance; SI units) and the maps' directories e_lt/ and e_mvs_lt/.

        Parameters
        ----------
        directory : str or Path
            Created if missing; files in it are overwritten.

        Returns
        -------
        Path
            The directory.
        """
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        self.e_lt.save(d / "e_lt", self.provenance)
        self.e_mvs_lt.save(d / "e_mvs_lt", self.provenance)
        meta = {
            "format_version": FORMAT_VERSION,
            "kind": "cobot-dt twin",
            "units": "SI (m, m/s); errors e = commanded - measured",
            "T_rdk": self.T_rdk.to_dict(), "T_lt": self.T_lt.to_dict(), "T_mvs": self.T_mvs.to_dict(),
            "u": jsonable(self.u, finite_only=False),
            "instruments": self.instruments,
            "provenance": self.provenance.to_dict() if self.provenance is not None else None,
        }
        if self.volume is not None:
            meta["volume"] = self.volume.to_dict()
        if self.position_u is not None:
            meta["position_uncertainty"] = self.position_u.to_dict()
        meta["uncertainty_calibration"] = self.conformal.to_dict()
        (d / "twin.json").write_text(json.dumps(meta, indent=2))
        return d

    @classmethod
    def load(cls, directory: str | Path) -> Twin:
        """Read a twin `save` wrote (format versions `READS`).

        Parameters
        ----------
        directory : str or Path
            The twin's directory.

        Returns
        -------
        Twin

        Raises
        ------
        ModelError
            twin.json is unreadable, of another format version, or has a missing or malformed
            entry; or a map cannot be loaded.
        """
        d = Path(directory)
        # Infinite degrees of freedom are written as Infinity (jsonable(u, finite_only=False));
        # any other non-finite number is refused by the reader.
        meta = read_meta(d / "twin.json", READS, "twin", infinite_ok=("dof",))
        try:
            return cls._load(d, meta)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
            raise ModelError(f"{d / 'twin.json'}: a missing or malformed entry ({exc!r})") from exc

    @classmethod
    def _load(cls, d: Path, meta: dict) -> Twin:
        if not isinstance(meta.get("u"), dict):
            raise ModelError(f"{d / 'twin.json'}: no 'u' object (the stated uncertainties)")
        u = {k: (np.array(v) if isinstance(v, list) else v) for k, v in meta["u"].items()}
        TwinUncertainty.from_mapping(u, str(d / "twin.json"))  # a malformed entry names the file
        return cls(RigidTransform.from_dict(meta["T_rdk"]), RigidTransform.from_dict(meta["T_lt"]),
                   RigidTransform.from_dict(meta["T_mvs"]), load_map(d / "e_lt"),
                   load_map(d / "e_mvs_lt"), u, meta.get("instruments", {}),
                   CalibratedVolume.from_dict(meta["volume"], f"{d / 'twin.json'}: volume")
                   if "volume" in meta else None,
                   PositionUncertainty.from_dict(meta["position_uncertainty"], str(d / "twin.json"))
                   if "position_uncertainty" in meta else None,
                   # twins saved before the record have none
                   Provenance.from_dict(meta["provenance"]) if meta.get("provenance") else None,
                   # twins saved before the conformal calibration: factor 1, method 'none'
                   ConformalScale.from_dict(meta["uncertainty_calibration"], str(d / "twin.json"))
                   if "uncertainty_calibration" in meta else ConformalScale())

