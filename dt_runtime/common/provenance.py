"""The traceability record of every model, twin, result and report.

Which software made it and when, from which input files (SHA-256), on which robot config,
measured with which instruments (certificate and stated uncertainty) and in what environment::

    rec = build(inputs=["data.csv"], robot="configs/robots/cobot_hc20_like.yaml",
                instruments=load_instruments("configs/instruments_example.yaml"))
    meta["provenance"] = rec.to_dict()          # JSON-ready; Provenance.from_dict reads it back
"""
from __future__ import annotations

import hashlib
import platform
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, date, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import DataError
from dt_runtime.common.outputs import final_path
from dt_runtime.common.paths import ROOT
from dt_runtime.common.version import DIST, git_commit, version

SCHEMA = 1  # version of the record's JSON layout
CHUNK = 1 << 20  # bytes read at a time when hashing: a large file costs no memory


# --------------------------------------------------------------------------- files

def sha256_file(path: str | Path) -> str:
    """SHA-256 (hex) of a file, read in chunks.

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    str
    """
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def shown_path(path: str | Path) -> str:
    """How a record names a file.

    Relative to the checkout when inside it, else absolute; a file of an output still being
    written names where it will be (`outputs.final_path`).

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    str
    """
    p = final_path(path).resolve()
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


@dataclass(frozen=True)
class FileRecord:
    """One input file: its path (shown_path), SHA-256 and size in bytes."""

    path: str
    sha256: str
    size_bytes: int

    @classmethod
    def of(cls, path: str | Path) -> FileRecord:
        """The record of an existing file (its shown path, SHA-256 and size).

        Parameters
        ----------
        path : str or Path
            The file.

        Returns
        -------
        FileRecord

        Raises
        ------
        DataError
            When `path` is not a file.
        """
        p = Path(path)
        if not p.is_file():
            raise DataError(f"{p}: no such file to record")
        return cls(shown_path(p), sha256_file(p), p.stat().st_size)

    @property
    def short(self) -> str:
        """The first 12 hex digits of the SHA-256, for display."""
        return self.sha256[:12]

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dict."""
        return {"path": self.path, "sha256": self.sha256, "size_bytes": self.size_bytes}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FileRecord:
        """The record `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        FileRecord
        """
        return cls(str(d["path"]), str(d["sha256"]), int(d["size_bytes"]))


def files_under(directory: str | Path) -> list[Path]:
    """Every regular file under a directory (e.g. a saved model), sorted: the files to hash.

    Parameters
    ----------
    directory : str or Path
        The directory.

    Returns
    -------
    list of Path
    """
    return sorted(p for p in Path(directory).rglob("*") if p.is_file())


# --------------------------------------------------------------------------- parts

@dataclass(frozen=True)
class Software:
    """The software that made a record: distribution name, version and git commit."""
    name: str
    version: str
    commit: str | None  # None outside a git checkout; "-dirty" when files differed

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dict."""
        return {"name": self.name, "version": self.version, "commit": self.commit}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Software:
        """The record `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        Software
        """
        return cls(str(d["name"]), str(d["version"]), d.get("commit"))


@dataclass(frozen=True)
class RobotRecord:
    """The robot: its config file (path and SHA-256), or only its name when the kinematic
    chain came from memory (or the robot is simulated)."""

    name: str | None = None
    path: str | None = None
    sha256: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dict."""
        return {"name": self.name, "path": self.path, "sha256": self.sha256}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RobotRecord:
        """The record `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        RobotRecord
        """
        return cls(d.get("name"), d.get("path"), d.get("sha256"))


# Instruments and certificates of a real campaign come from a YAML the user writes
# (configs/instruments_example.yaml), validated by `InstrumentsConfig`; simulated instruments
# state what their simulator config states (dt_runtime.workflows.demo).
@dataclass(frozen=True)
class Instrument:
    """One instrument of the campaign. uncertainty: the stated uncertainty as the certificate
    (or the simulator config) gives it: {"kind": "standard"|"expanded"|"MPE", "k": coverage
    factor or None, "text": the statement in words, "terms": {name: {"value", "unit"}}}."""

    role: str  # tracker, camera, robot, thermometer, ...
    kind: str | None = None  # what it is, e.g. "laser tracker"
    driver: str | None = None  # the driver that read it (drivers.registry name), if known
    model: str | None = None
    serial: str | None = None
    certificate: str | None = None  # calibration certificate reference
    calibration_date: str | None = None  # ISO date
    valid_until: str | None = None
    uncertainty: Mapping[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dict."""
        return {"role": self.role, "kind": self.kind, "driver": self.driver, "model": self.model,
                "serial": self.serial, "certificate": self.certificate, "calibration_date": self.calibration_date,
                "valid_until": self.valid_until,
                "uncertainty": dict(self.uncertainty) if self.uncertainty is not None else None}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Instrument:
        """The record `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        Instrument
        """
        return cls(str(d["role"]), d.get("kind"), d.get("driver"), d.get("model"), d.get("serial"),
                   d.get("certificate"), d.get("calibration_date"), d.get("valid_until"), d.get("uncertainty"))


@dataclass(frozen=True)
class Environment:
    """The campaign's temperature (deg C) over the rows that state it."""

    temperature_min_c: float
    temperature_max_c: float
    temperature_mean_c: float
    n: int

    @classmethod
    def of(cls, temperature: np.ndarray | Sequence[float] | None) -> Environment | None:
        """The environment of a temperature column.

        Parameters
        ----------
        temperature : array-like or None
            Temperatures in deg C; non-finite values are ignored.

        Returns
        -------
        Environment or None
            None without a column or without a finite value.
        """
        if temperature is None:
            return None
        t = np.asarray(temperature, dtype=float).ravel()
        t = t[np.isfinite(t)]
        if t.size == 0:
            return None
        return cls(float(t.min()), float(t.max()), float(t.mean()), int(t.size))

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dict (``{"temperature_c": {min, max, mean, n}}``)."""
        return {"temperature_c": {"min": self.temperature_min_c, "max": self.temperature_max_c,
                                  "mean": self.temperature_mean_c, "n": self.n}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Environment:
        """The record `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        Environment
        """
        t = d["temperature_c"]
        return cls(float(t["min"]), float(t["max"]), float(t["mean"]), int(t["n"]))


# --------------------------------------------------------------------------- the record

@dataclass(frozen=True)
class Provenance:
    """Software (name, version, commit), creation time (UTC, ISO 8601), host Python, input files
    with their SHA-256, the robot config, the instruments and the environment."""

    software: Software
    created: str
    python: str
    inputs: tuple[FileRecord, ...] = ()
    robot: RobotRecord | None = None
    instruments: tuple[Instrument, ...] = ()
    environment: Environment | None = None
    schema: int = SCHEMA

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dict."""
        return {"schema": self.schema, "software": self.software.to_dict(), "created": self.created,
                "python": self.python, "inputs": [f.to_dict() for f in self.inputs],
                "robot": self.robot.to_dict() if self.robot else None,
                "instruments": [i.to_dict() for i in self.instruments],
                "environment": self.environment.to_dict() if self.environment else None}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Provenance:
        """The record `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.

        Returns
        -------
        Provenance

        Raises
        ------
        DataError
            Naming what is missing or malformed.
        """
        try:
            return cls(Software.from_dict(d["software"]), str(d["created"]), str(d["python"]),
                       tuple(FileRecord.from_dict(f) for f in d.get("inputs") or ()),
                       RobotRecord.from_dict(d["robot"]) if d.get("robot") else None,
                       tuple(Instrument.from_dict(i) for i in d.get("instruments") or ()),
                       Environment.from_dict(d["environment"]) if d.get("environment") else None,
                       int(d.get("schema", SCHEMA)))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"malformed provenance record ({type(exc).__name__}: {exc})") from exc

    def renewed(self) -> Provenance:
        """The same inputs, robot, instruments and environment, made now by this software."""
        return replace(self, software=software(), created=now_utc(), python=platform.python_version())


def software() -> Software:
    """This software: distribution name, installed version and git commit.

    Returns
    -------
    Software
    """
    return Software(DIST, version(), git_commit())


def now_utc() -> str:
    """The current time, UTC, ISO 8601 to the second.

    Returns
    -------
    str
    """
    return datetime.now(UTC).isoformat(timespec="seconds")


def build(inputs: Iterable[str | Path | FileRecord] = (), robot: str | Path | None = None,
          robot_name: str | None = None, instruments: Iterable[Instrument] = (),
          temperature: np.ndarray | Sequence[float] | None = None,
          environment: Environment | None = None) -> Provenance:
    """The traceability record for now.

    Parameters
    ----------
    inputs : iterable of str, Path or FileRecord, optional
        Input files, hashed (existing files only; the same file once).
    robot : str or Path, optional
        A robot config file (hashed when it exists).
    robot_name : str, optional
        The robot's name (e.g. the chain's, when it came from memory).
    instruments : iterable of Instrument, optional
        The campaign's instruments.
    temperature : array-like, optional
        Temperature column the environment is taken from, unless `environment` is given.
    environment : Environment, optional
        The environment, as is.

    Returns
    -------
    Provenance
    """
    files: list[FileRecord] = []
    for f in inputs:
        rec = f if isinstance(f, FileRecord) else FileRecord.of(f) if Path(f).is_file() else None
        if rec is not None and all(rec.path != g.path for g in files):
            files.append(rec)
    rob = None
    if robot is not None and Path(robot).is_file():
        rob = RobotRecord(robot_name, shown_path(robot), sha256_file(robot))
    elif robot is not None or robot_name is not None:
        rob = RobotRecord(robot_name or str(robot))
    env = environment if environment is not None else Environment.of(temperature)
    return Provenance(software(), now_utc(), platform.python_version(), tuple(files), rob,
                      tuple(instruments), env)


# --------------------------------------------------------------------------- instruments YAML

Unit = Literal["m", "mm", "um", "nm", "m/m", "mm/m", "um/m", "ppm", "px", "rad", "mrad", "urad", "deg",
               "arcsec", "K", "degC", "1"]


class QuantityConfig(Frozen):
    """A value with its unit, e.g. ``{value: 15, unit: um}``."""
    value: float = Field(allow_inf_nan=False)
    unit: Unit


class UncertaintyConfig(Frozen):
    """A stated uncertainty: in words (text) and/or as terms with units, e.g. a laser tracker's
    MPE 15 um + 6 um/m: terms {constant: {value: 15, unit: um}, per_length: {value: 6, unit: um/m}}."""

    kind: Literal["standard", "expanded", "MPE"] = "standard"
    k: float | None = Field(None, gt=0)  # coverage factor of an expanded uncertainty
    text: str | None = None
    terms: dict[str, QuantityConfig] = {}

    @model_validator(mode="after")
    def _stated(self) -> UncertaintyConfig:
        if not self.text and not self.terms:
            raise ValueError("state the uncertainty as 'text' and/or 'terms' (value and unit per term)")
        if self.kind == "expanded" and self.k is None:
            raise ValueError("an expanded uncertainty needs its coverage factor 'k'")
        return self


class InstrumentConfig(Frozen):
    """One instrument entry of an instruments YAML: role, kind, identity, certificate and dates,
    the driver that reads it and its stated uncertainty.
    """
    role: str = Field(pattern=r"^[a-z][a-z0-9_]*$")  # tracker, camera, robot, thermometer, ...
    kind: str = Field(min_length=1)
    model: str | None = None
    serial: str | None = None
    certificate: str | None = None
    calibration_date: date | None = None
    valid_until: date | None = None
    driver: str | None = None
    uncertainty: UncertaintyConfig

    @model_validator(mode="after")
    def _dates(self) -> InstrumentConfig:
        if self.calibration_date and self.valid_until and self.valid_until < self.calibration_date:
            raise ValueError(f"valid_until {self.valid_until} is before calibration_date {self.calibration_date}")
        return self


class InstrumentsConfig(Frozen):
    """The instruments of a measurement campaign (configs/instruments_example.yaml), one entry
    per role (tracker, camera, robot, thermometer, ...)."""

    campaign: str | None = None
    instruments: list[InstrumentConfig] = Field(min_length=1)

    @model_validator(mode="after")
    def _roles(self) -> InstrumentsConfig:
        roles = [c.role for c in self.instruments]
        twice = sorted({r for r in roles if roles.count(r) > 1})
        if twice:
            raise ValueError(f"role {twice[0]!r} given twice; one entry per role")
        return self

    def records(self) -> tuple[Instrument, ...]:
        """The entries as provenance records (dates as ISO text).

        Returns
        -------
        tuple of Instrument
        """
        out = []
        for c in self.instruments:
            u = c.uncertainty
            out.append(Instrument(c.role, c.kind, c.driver, c.model, c.serial, c.certificate,
                                  c.calibration_date.isoformat() if c.calibration_date else None,
                                  c.valid_until.isoformat() if c.valid_until else None,
                                  {"kind": u.kind, "k": u.k, "text": u.text,
                                   "terms": {n: q.model_dump() for n, q in u.terms.items()}}))
        return tuple(out)


def load_instruments(path: str | Path) -> tuple[Instrument, ...]:
    """The instrument records of an instruments YAML.

    Parameters
    ----------
    path : str or Path
        The YAML file (e.g. ``configs/instruments_example.yaml``).

    Returns
    -------
    tuple of Instrument

    Raises
    ------
    ConfigError
        Naming the file, key, value and what is allowed.
    """
    return load_yaml(path, InstrumentsConfig).records()  # the kernel turns an impossible date into ConfigError
