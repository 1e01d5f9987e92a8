"""Effects of the user's own, beyond the catalogue, without editing the project.

Declared in YAML as regressors built from the data's columns (`--effects-file`; a fitted model
keeps the declaration), or written in Python as an `Effect` subclass published under the entry
point group `cobot_dt.effects`. Nothing here is registered in the process: the effects go into
the `Catalogue` of one call. See docs/effects.md ("Your own effects").
"""
from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from dt_kernel.config import Frozen, load_yaml, validate
from dt_kernel.errors import DataError
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs

ENTRY_POINT_GROUP = "cobot_dt.effects"
_NAME = re.compile(r"^[a-z][a-z0-9_]{0,39}$")


class TermSpec(Frozen):
    """One term of a declared effect: a column minus its reference, as a TCP offset along `axes`
    (cartesian) or as joint offsets through the Jacobian (joints).
    """
    column: str = Field(min_length=1)
    reference: float = 0.0
    unit: str = "1"
    space: Literal["cartesian", "joints"] = "cartesian"
    axes: tuple[Literal["x", "y", "z"], ...] = ("x", "y", "z")
    joints: tuple[int, ...] | None = None  # 1-based joint numbers (space: joints); None: all

    @field_validator("joints")
    @classmethod
    def _joints(cls, v):
        if v is not None and (not v or min(v) < 1):
            raise ValueError("joint numbers start at 1")
        return v


class EffectSpec(Frozen):
    """One declared effect: its name, the factor the diagnosis names, its terms."""
    name: str
    factor: str = Field(min_length=3)
    terms: tuple[TermSpec, ...] = Field(min_length=1)

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not _NAME.match(v):
            raise ValueError(f"{v!r}: lower-case letters, digits and _, starting with a letter")
        return v


class EffectsFile(Frozen):
    """An effects YAML (`--effects-file`): one or more declared effects."""
    effects: tuple[EffectSpec, ...] = Field(min_length=1)


class DeclaredEffect(Effect):
    """An effect built from a declaration (`EffectSpec`): one regressor per term and axis/joint."""

    spec: EffectSpec
    source: str = ""  # where it was declared (the YAML file, a saved model), for the errors

    def __reduce__(self):
        # Its class is made per declaration (`declare`) and cannot be found by name in another
        # process: a diagnosis's worker rebuilds it from the declaration.
        return declare, (self.spec, self.source)

    def _where(self) -> str:
        return f" (declared in {self.source})" if self.source else ""

    def build(self, inp: Inputs, chain: Chain | None, hyper: dict[str, float] | None = None) -> Block:
        """The regressor block; a missing column names the declaring file and the data's columns.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain or None
            The robot's kinematic chain (needed for joint-space terms).
        hyper : dict, optional
            Not used (a declared effect has no nonlinear parameters).

        Returns
        -------
        Block

        Raises
        ------
        DataError
            When the data lack a column the declaration reads.
        """
        # The catalogue's message names the missing column; a declared one may be a typo in the
        # user's file, so name the file and the columns the data do have.
        missing = [c for c in self.columns if inp.get(c) is None]
        if missing:
            raise DataError(f"effect '{self.name}'{self._where()} reads the column(s) {', '.join(missing)}, which "
                            f"the data do not have; their columns: {', '.join(columns_of(inp)) or 'none'}")
        return super().build(inp, chain, hyper)

    def regressors(self, inp: Inputs, chain: Chain) -> Block:
        """The block: one regressor per term and axis (cartesian) or joint (joints).

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
        cols, names, units = [], [], []
        J = chain.jacobian(inp.column("joints")) if self.needs_chain else None
        for i, term in enumerate(self.spec.terms):
            x = inp.column(term.column) - term.reference
            if term.space == "cartesian":
                for ax in term.axes:
                    a = np.zeros((inp.n, 3))
                    a[:, "xyz".index(ax)] = x
                    cols.append(a)
                    names.append(f"{term.column}_{ax}")
                    units.append(f"m/{term.unit}")
            else:
                assert J is not None
                dof = J.shape[2]
                bad = [j for j in (term.joints or ()) if j > dof]
                if bad:
                    raise DataError(f"effect '{self.name}'{self._where()}: terms.{i}.joints names joint(s) "
                                    f"{', '.join(map(str, bad))}, beyond the robot's {dof} (joints are 1..{dof})")
                for j in term.joints or range(1, dof + 1):
                    cols.append(-J[:, :, j - 1] * x[:, None])  # e = -J dq, dq_j = c_j x
                    names.append(f"q{j}_per_{term.column}")
                    units.append(f"rad/{term.unit}")
        return Block(self.name, np.stack(cols, axis=2), tuple(names), tuple(units))


def columns_of(inp: Inputs) -> list[str]:
    """The data's columns by their file names (q1..qk for the joints), for error messages.

    Parameters
    ----------
    inp : Inputs
        The data's columns.

    Returns
    -------
    list of str
    """
    out = [c for c in ("speed", "temperature", "payload", "t") if inp.get(c) is not None]
    if inp.joints is not None:
        out += [f"q{j + 1}" for j in range(inp.joints.shape[1])]
    return out + sorted(inp.extra or {})


def declare(spec: EffectSpec, source: str = "") -> Effect:
    """The effect a declaration describes (a class of its own, so it has its name and columns).

    Parameters
    ----------
    spec : EffectSpec
        The declaration.
    source : str, optional
        Where it was declared, for errors.

    Returns
    -------
    Effect
    """
    joints = any(t.space == "joints" for t in spec.terms)
    columns = tuple(dict.fromkeys((["joints"] if joints else []) + [t.column for t in spec.terms]))
    cls = type(f"Declared_{spec.name}", (DeclaredEffect,),
               {"name": spec.name, "columns": columns, "needs_chain": joints, "factor": spec.factor, "spec": spec,
                "source": source})
    return cls()


def read_file(path: str | Path) -> list[Effect]:
    """The effects declared in a YAML file (ConfigError names the key, the value and what is allowed).

    Parameters
    ----------
    path : str or Path
        The effects YAML.

    Returns
    -------
    list of Effect
    """
    return [declare(s, str(path)) for s in load_yaml(path, EffectsFile).effects]


def from_dict(d: dict) -> Effect:
    """A declaration kept in a saved model (`EffectSpec` as a dict).

    Parameters
    ----------
    d : dict
        The declaration.

    Returns
    -------
    Effect
    """
    return declare(validate(EffectSpec, d, "<saved model>"), "a saved model")


def entry_point_effects() -> list[tuple[str, Effect]]:
    """(entry point name, effect) of every installed package's `cobot_dt.effects` entry point."""
    out = []
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
            effect = obj() if isinstance(obj, type) else obj
        except Exception as exc:  # a broken plugin must say which one, not stop the catalogue
            raise DataError(f"effect plugin {ep.name!r} ({ep.value}) does not load: {exc}") from exc
        if not isinstance(effect, Effect):
            raise DataError(f"effect plugin {ep.name!r} ({ep.value}) is not an Effect subclass")
        out.append((ep.name, effect))
    return out
