"""Which robot: one reference text for a catalogue arm, a robot config YAML or a URDF, and the
catalogue of nominal kinematics (configs/robots/catalogue/, each entry citing its source).

`resolve` turns what a user wrote into a `RobotRef`, whose `text` is the stable form a saved
model, a campaign manifest or a result keeps; `load` gives the chain of any such text (parsed
once per process). See docs/robots.md.
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

from dt_kernel.config import load_yaml
from dt_kernel.errors import ConfigError, DataError
from dt_runtime.common.paths import CONFIGS
from dt_runtime.frames.kinematics import Chain, RobotModel, chain_from_urdf, load_robot

CATALOGUE = CONFIGS / "robots" / "catalogue"
NAME = re.compile(r"^[a-z][a-z0-9_]*$")  # a catalogue name: no dot, no slash
TOOL_KEY = "?tool_mm="
URDF_SUFFIXES = (".urdf",)
YAML_SUFFIXES = (".yaml", ".yml")


def names() -> list[str]:
    """The catalogue's arm names, sorted."""
    return sorted(p.stem for p in CATALOGUE.glob("*.yaml"))


def catalogue_file(name: str, where: str | Path = "--robot") -> Path:
    """The catalogue entry of `name`; an unknown name is a ConfigError listing the catalogue.

    Parameters
    ----------
    name : str
        The catalogue name, e.g. "ur5e".
    where : str or Path, optional
        What the error names as the source.

    Returns
    -------
    Path
    """
    p = CATALOGUE / f"{name}.yaml"
    if not NAME.match(name) or not p.is_file():
        raise ConfigError(where, "robot", name, "a catalogue arm (" + ", ".join(names()) + "; `dt robots` lists "
                          "them), a robot config YAML or a URDF file")
    return p


@dataclass(frozen=True)
class RobotRef:
    """A resolved robot reference: the file it reads (absolute), the catalogue name if it is one,
    the URDF link the chain ends at, and a tool offset (m, flange frame) appended to the chain.

    Its text, for example::

        ur5e                              a catalogue arm (configs/robots/catalogue/ur5e.yaml)
        robots/ur10.yaml                  a robot config (saved relative to configs/ when shipped there)
        /data/arm.urdf#tool0              a vendor's URDF, the chain ending at link tool0 (default: the
                                          URDF's last link)
        ur5e?tool_mm=0.5,-1.2,101.3       any of these with a tool offset (mm, flange frame) appended:
                                          how a tool offset fitted from the data (`frames.tool_fit`)
                                          travels with a saved model
    """

    file: Path
    catalogue: str | None = None
    link: str | None = None
    tool_m: tuple[float, float, float] | None = None

    @property
    def text(self) -> str:
        """The stable reference: the catalogue name, else the path relative to configs/ when the
        file is shipped there, else absolute; then '#link' and '?tool_mm=x,y,z'."""
        if self.catalogue is not None:
            out = self.catalogue
        else:
            try:
                out = str(self.file.relative_to(CONFIGS))
            except ValueError:
                out = str(self.file)
        if self.link is not None:
            out += f"#{self.link}"
        if self.tool_m is not None:
            out += TOOL_KEY + ",".join(f"{v * 1000.0:.6f}" for v in self.tool_m)
        return out

    @property
    def is_urdf(self) -> bool:
        """Whether the file is a URDF (by its suffix)."""
        return self.file.suffix.lower() in URDF_SUFFIXES

    def with_tool(self, offset_m) -> RobotRef:
        """This reference with a tool offset.

        Parameters
        ----------
        offset_m : array-like
            (3,) tool offset, m.

        Returns
        -------
        RobotRef
        """
        return replace(self, tool_m=tuple(float(v) for v in offset_m))  # type: ignore[arg-type]


def _split(text: str) -> tuple[str, str | None, tuple[float, float, float] | None]:
    tool = None
    if TOOL_KEY in text:
        text, spec = text.split(TOOL_KEY, 1)
        try:
            vals = [float(v) / 1000.0 for v in spec.split(",")]
        except ValueError:
            vals = []
        if len(vals) != 3:
            raise ConfigError("--robot", "tool_mm", spec, "three numbers x,y,z in mm (the tool offset in the flange "
                              "frame), e.g. ur5e?tool_mm=0,0,100")
        tool = (vals[0], vals[1], vals[2])
    link = None
    if "#" in text:
        text, link = text.split("#", 1)
    return text, link or None, tool


def resolve(ref: str | Path | RobotRef, bases: Sequence[Path] = ()) -> RobotRef:
    """What a user wrote (--robot, a mapping's or a manifest's `robot:`, a saved model's reference)
    as a RobotRef: a catalogue name, else a YAML or URDF file relative to each of `bases` in turn,
    else to the working directory, else to configs/ (absolute paths as they are). DataError if no file is found.

    Parameters
    ----------
    ref : str, Path or RobotRef
        The reference as written.
    bases : sequence of Path, optional
        Directories a relative path is looked for in first.

    Returns
    -------
    RobotRef
    """
    if isinstance(ref, RobotRef):
        return ref
    base, link, tool = _split(str(ref))
    if NAME.match(base):
        if link is not None:
            raise ConfigError("--robot", "robot", str(ref), "'#link' only after a URDF file")
        return RobotRef(catalogue_file(base).resolve(), base, None, tool)
    p = Path(base)
    tried = [p] if p.is_absolute() else [b / p for b in bases] + [Path.cwd() / p, CONFIGS / p]
    for cand in tried:
        if cand.is_file():
            found = cand.resolve()
            break
    else:
        raise DataError(f"robot {ref}: no such file (looked for {', '.join(map(str, dict.fromkeys(tried)))}); "
                        f"a robot is a catalogue arm ({', '.join(names())}), a robot config YAML or a URDF")
    suffix = found.suffix.lower()
    if suffix not in URDF_SUFFIXES + YAML_SUFFIXES:
        raise ConfigError(found, "<file>", suffix or found.name, "a robot config (.yaml, .yml) or a URDF (.urdf)")
    if link is not None and suffix not in URDF_SUFFIXES:
        raise ConfigError(found, "<file>", str(ref), "'#link' only after a URDF file (a YAML names it as tool_link)")
    return RobotRef(found, None, link, tool)


def reference(ref: str | Path | RobotRef | None, bases: Sequence[Path] | None = None) -> str | None:
    """The stable text of a robot reference (None stays None); a relative path is looked for in
    `bases` (default: the working directory), then in configs/.

    Parameters
    ----------
    ref : str, Path, RobotRef or None
        The reference as written.
    bases : sequence of Path, optional
        Directories a relative path is looked for in.

    Returns
    -------
    str or None
    """
    return None if ref is None else resolve(ref, [Path.cwd()] if bases is None else bases).text


def record(ref: str | Path | None) -> tuple[Path | None, str | None]:
    """What a traceability record keeps of a robot reference: the file it reads (to hash) and the
    reference's text (None, None without a robot; the text alone if it no longer resolves).

    Parameters
    ----------
    ref : str, Path or None
        The reference.

    Returns
    -------
    file : Path or None
    text : str or None
    """
    if ref is None:
        return None, None
    try:
        r = resolve(ref)
    except (ConfigError, DataError):
        return None, str(ref)
    return r.file, r.text


def load(ref: str | Path | RobotRef, bases: Sequence[Path] = ()) -> Chain:
    """The kinematic chain of a robot reference (the forms: `RobotRef`), parsed once per process.

    Parameters
    ----------
    ref : str, Path or RobotRef
        The reference.
    bases : sequence of Path, optional
        Directories a relative path is looked for in first.

    Returns
    -------
    Chain
    """
    r = resolve(ref, bases)
    if not r.file.is_file():  # the cache must not hide a file removed since
        raise DataError(f"robot {r.text}: no such file {r.file}")
    return _load(r.file, r.link, r.tool_m)


@lru_cache(maxsize=16)
def _load(file: Path, link: str | None, tool: tuple[float, float, float] | None) -> Chain:
    chain = chain_from_urdf(file, link) if file.suffix.lower() in URDF_SUFFIXES else load_robot(file)
    return chain if tool is None else chain.with_tool(tool)


@dataclass(frozen=True)
class Entry:
    """One catalogue arm as `dt robots` lists it."""

    name: str
    dof: int
    vendor: str
    description: str
    sources: list[dict]
    file: str

    def to_dict(self) -> dict:
        """The entry as a JSON-ready dict."""
        return {"name": self.name, "dof": self.dof, "vendor": self.vendor, "description": self.description,
                "sources": self.sources, "file": self.file}


def catalogue() -> list[Entry]:
    """Every catalogue arm: name, number of joints, vendor, description and sources."""
    out = []
    for name in names():
        f = CATALOGUE / f"{name}.yaml"
        m = load_yaml(f, RobotModel)
        out.append(Entry(name, load(name).dof, m.vendor, m.description,
                         [s.model_dump(exclude_defaults=True) for s in m.sources], str(f.relative_to(CONFIGS))))
    return out
