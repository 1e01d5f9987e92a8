"""A campaign on disk: its phase files (`measurements.campaign_files`) and the manifest that names
them, the robot config, the instruments and the drivers that measured (`campaign.yaml`).

    registration: registration.csv      # required (three-line registration, axis + distance)
    doe: doe.csv                        # required
    validation: validation.csv          # optional: measured without correction
    robot: robots/cobot_hc20_like.yaml  # robot config: relative to this file, else to configs/
    instruments: instruments.yaml       # optional: instruments and certificates (provenance)
    drivers: {robot: sim, tracker: sim, camera: sim_images}   # optional: what measured

`dt demo` writes one (DIR/campaign/) from its simulated campaign; `dt calibrate --campaign DIR`
reads it. Every file the twin is built from is hashed into its provenance.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import DataError
from dt_runtime.common.jsonsafe import jsonable
from dt_runtime.common.outputs import final_path
from dt_runtime.common.paths import beside
from dt_runtime.common.progress import Progress
from dt_runtime.common.provenance import Instrument, files_under, load_instruments
from dt_runtime.common.provenance import build as build_provenance
from dt_runtime.frames import robots
from dt_runtime.frames.kinematics import Chain
from dt_runtime.measurements.campaign_files import check_robot, read_phase, write_phase
from dt_runtime.measurements.phase import PhaseData
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.workflows.calibrate import (
    Calibrated,
    CalibrationOptions,
    Campaign,
    arrays,
    calibrate,
    figures,
    validation,
    validity_of,
)

MANIFEST = "campaign.yaml"


class Manifest(Frozen):
    """campaign.yaml, as validated (the module docstring shows one; docs/campaign-files.md).

    Attributes
    ----------
    registration, doe : str
        The phase files, relative to the manifest.
    validation : str or None
        The validation phase file (measured without correction).
    robot : str or None
        The robot config: relative to the manifest, else to configs/, or a catalogue arm.
    instruments : str or None
        The instruments YAML (certificates, provenance).
    drivers : dict
        Role -> the driver that measured.
    seed : int or None
        The campaign's seed: `dt calibrate`'s default (the demo's plan seed).
    """

    registration: str
    doe: str
    validation: str | None = None
    robot: str | None = None
    instruments: str | None = None
    drivers: dict[str, str] = {}
    seed: int | None = None  # the campaign's seed: `dt calibrate`'s default (the demo's plan seed)


@dataclass
class CampaignFiles:
    """Where a campaign's parts are (absolute paths); `load` reads and checks them."""

    registration: Path
    doe: Path
    validation: Path | None = None
    robot: str | None = None  # a robot reference (frames.robots)
    instruments: Path | None = None
    drivers: dict[str, str] | None = None
    manifest: Path | None = None
    seed: int | None = None

    def inputs(self) -> list[Path]:
        """The files the twin is built from (hashed into its provenance)."""
        return [p for p in (self.manifest, self.registration, self.doe, self.validation, self.instruments) if p]

    def load(self) -> Campaign:
        """Read the phases; DataError if a file is malformed, in other units, or of another
        robot than the robot config (`campaign_files.check_robot`)."""
        chain = self.chain()
        phases: list[PhaseData | None] = []
        for name, path in (("registration", self.registration), ("doe", self.doe), ("validation", self.validation)):
            if path is None:
                phases.append(None)
                continue
            data = read_phase(path, name, registration=name == "registration")
            if chain is not None:
                check_robot(data, chain, str(path))
            phases.append(data)
        reg, doe, val = phases
        assert reg is not None and doe is not None
        return Campaign(reg, doe, val)

    def chain(self) -> Chain | None:
        """The robot config's kinematic chain (`frames.robots.load`), None without a robot."""
        return robots.load(self.robot) if self.robot is not None else None


def resolve_robot(ref: str | Path, base: Path) -> str:
    """A robot named in a manifest or on the command line, as its reference (`frames.robots`): a
    catalogue arm, or a robot config or URDF relative to `base`, else under configs/ (the shipped
    robots: robots/ur10.yaml).

    Parameters
    ----------
    ref : str or Path
        The robot as named.
    base : Path
        The directory a relative file is looked for in first.

    Returns
    -------
    str
        The reference's text form (`frames.robots.resolve`).
    """
    return robots.resolve(ref, [base]).text


def read_manifest(path: str | Path) -> CampaignFiles:
    """A campaign directory (its campaign.yaml) or a manifest file, its files checked to exist.

    Parameters
    ----------
    path : str or Path
        The campaign directory or its manifest.

    Returns
    -------
    CampaignFiles
        Absolute paths (the phases are read by `CampaignFiles.load`).

    Raises
    ------
    DataError
        No manifest there, or a file it names does not exist.
    ConfigError
        The manifest has a bad key or value.
    """
    p = Path(path)
    if p.is_dir():
        p = p / MANIFEST
    if not p.is_file():
        raise DataError(f"{p}: no campaign manifest (a campaign directory holds {MANIFEST}, "
                        "see docs/campaign-files.md)")
    m = load_yaml(p, Manifest)
    base = p.parent

    def f(rel: str | None) -> Path | None:
        if rel is None:
            return None
        q = beside(base, rel)
        if not q.is_file():
            raise DataError(f"{p}: the file {rel} it names does not exist")
        return q

    reg, doe = f(m.registration), f(m.doe)
    assert reg is not None and doe is not None
    return CampaignFiles(reg, doe, f(m.validation), resolve_robot(m.robot, base) if m.robot else None,
                         f(m.instruments), dict(m.drivers) or None, p, m.seed)


def write_campaign(directory: str | Path, campaign: Campaign, robot: str | None = None, seed: int | None = None,
                   instruments: tuple[Instrument, ...] = (), drivers: dict[str, str] | None = None,
                   campaign_name: str | None = None) -> CampaignFiles:
    """Write the phases, the instruments YAML (the records' certificate statements) and the
    manifest; `robot`: the robot config's reference as the manifest keeps it; `seed`: the one
    `dt calibrate` uses by default (the same twin as the demo's).

    Parameters
    ----------
    directory : str or Path
        Created if missing; its files are overwritten.
    campaign : Campaign
        The phases (SI; written in the campaign files' units, mm).
    robot : str or None
        The robot reference as the manifest keeps it.
    seed : int or None
        The campaign's seed.
    instruments : tuple of Instrument
        The instruments' records (written to instruments.yaml when given).
    drivers : dict or None
        Role -> the driver that measured.
    campaign_name : str or None
        The campaign's name in instruments.yaml.

    Returns
    -------
    CampaignFiles
        The manifest read back (`read_manifest`).
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    names = {"registration": campaign.registration, "doe": campaign.doe, "validation": campaign.validation}
    man: dict = {}
    for name, data in names.items():
        if data is not None:
            write_phase(d / f"{name}.csv", data)
            man[name] = f"{name}.csv"
    if instruments:
        doc = {"campaign": campaign_name, "instruments": [
            {k: v for k, v in i.to_dict().items() if v is not None} for i in instruments]}
        (d / "instruments.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        man["instruments"] = "instruments.yaml"
    if robot is not None:
        man["robot"] = robot
    if drivers:
        man["drivers"] = dict(drivers)
    if seed is not None:
        man["seed"] = int(seed)
    (d / MANIFEST).write_text("# A calibration campaign (docs/campaign-files.md): `dt calibrate --campaign DIR`\n"
                              + yaml.safe_dump(man, sort_keys=False))
    return read_manifest(d)


@dataclass
class CalibrationRun:
    """What `calibrate_campaign` made.

    Attributes
    ----------
    summary : dict
        mm, JSON-ready: what `dt calibrate --json` prints and TWIN/summary.json holds.
    arrays : dict
        Raw arrays (SI) for the report's figures.
    calibrated : Calibrated
        The calibration itself.
    """

    summary: dict  # mm, JSON-ready: what `dt calibrate --json` prints and TWIN/summary.json holds
    arrays: dict  # raw arrays (SI) for the report's figures
    calibrated: Calibrated


def calibrate_campaign(files: CampaignFiles, options: CalibrationOptions, out: str | Path,
                       lt_model: HybridModel | None = None, lt_model_dir: str | Path | None = None,
                       progress: Progress | None = None, catalogue=None) -> CalibrationRun:
    """`dt calibrate`: read and check the campaign's files, calibrate, validate on the
    validation phase if there is one, and write the twin (OUT, `Twin.load` reads it) with its
    summary.json. Nothing is written if any input is bad. `catalogue`: the `effects.Catalogue`
    that `options.effects` refer to (`calibrate`).

    Parameters
    ----------
    files : CampaignFiles
        The campaign (`read_manifest`).
    options : CalibrationOptions
        How the maps are fitted and the volume drawn.
    out : str or Path
        The twin's directory (twin.json, the maps, summary.json).
    lt_model : HybridModel or None
        The e_LT map's configuration (e.g. a `dt fit` model's); None: `options.effects` + GP.
    lt_model_dir : str, Path or None
        Where `lt_model` was read from: its files are hashed into the provenance.
    progress : Progress or None
        Where progress notes go.
    catalogue : Catalogue or None
        The effects `options.effects` refer to.

    Returns
    -------
    CalibrationRun

    Raises
    ------
    DataError
        A phase file is malformed, in other units, or of another robot than the robot config.
    """
    progress = progress or Progress(enabled=False)
    campaign = files.load()
    instruments = load_instruments(files.instruments) if files.instruments else ()
    progress.note(f"campaign: {campaign.registration.n} registration, {campaign.doe.n} DOE"
                  + (f", {campaign.validation.n} validation" if campaign.validation else "") + " positionings")
    c = calibrate(campaign, options, files.robot, files.drivers, progress, lt_model, catalogue)
    temps = np.concatenate([np.asarray(p.temperature, dtype=float)
                            for p in (campaign.registration, campaign.doe, campaign.validation) if p is not None])
    extra = files_under(lt_model_dir) if lt_model_dir is not None else []
    chain = files.chain()
    prov = build_provenance([*files.inputs(), *extra], robot=robots.record(files.robot)[0],
                            robot_name=chain.name if chain is not None else None,
                            instruments=instruments, temperature=temps[np.isfinite(temps)])
    c.twin.provenance = prov
    summary = {"campaign": str(final_path(files.manifest or files.doe)), **figures(c)}
    v = validation(c, campaign.validation) if campaign.validation is not None else None
    if v is not None:
        summary["validation"] = v.summary()
    summary["validity"] = validity_of(c, v, str(final_path(files.manifest.parent)) if files.manifest else None)
    summary["units"] = "mm; errors e = commanded - measured, in the global frame GL"
    summary["provenance"] = prov.to_dict()
    out = Path(out)
    c.twin.save(out)
    summary["twin"] = str(final_path(out))  # not the staged directory it is written in (common.outputs)
    (out / "summary.json").write_text(json.dumps(jsonable(summary), indent=2))
    progress.note(f"wrote the twin in {out}")
    return CalibrationRun(summary, arrays(c), c)
