"""What a diagnosis is asked: `DiagnoseOptions`, one frozen, validated record that `diagnose` and
`prepare` (analysis.diagnose) read, so a call states its choices once, by name. docs/library.md.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from dt_kernel.errors import ConfigError
from dt_runtime.analysis.ranking import ALPHA
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models import effects as fx
from dt_runtime.models.gp import GPOptions
from dt_runtime.models.hybrid import GP_INPUTS, HybridModel

__all__ = ["DiagnoseOptions"]


def _names(field: str, value: object) -> tuple[str, ...]:
    # a lone string would be read letter by letter as effect names: refused, not split
    if isinstance(value, str) or not isinstance(value, Sequence) or not all(isinstance(v, str) for v in value):
        raise _fail(field, value, "a sequence of names, e.g. ('geometric', 'backlash')")
    return tuple(value)


def _fail(field: str, value: object, allowed: str) -> ConfigError:
    # ConfigError's "file" is the record: the message reads "DiagnoseOptions: key 'folds': value 1 ..."
    return ConfigError("DiagnoseOptions", field, value, allowed)


@dataclass(frozen=True)
class DiagnoseOptions:
    """The choices of one diagnosis (`analysis.diagnose.diagnose` and `prepare`).

    Sequences are stored as tuples; every field is checked when the record is made, and an error
    names the field, the value seen and what is allowed (`ConfigError`).

    Parameters
    ----------
    model : HybridModel, str, Path or None
        The starting model, fitted or not, or a saved model's directory. When given, its effects,
        GP inputs, robot, GP options and ridge replace `effects`, `gp_inputs`, `robot` and
        `gp_options`.
    effects : tuple of str
        The starting model's effects when there is no `model`.
    gp_inputs : str
        The starting model's GP inputs when there is no `model`: one of ``GP_INPUTS``.
    robot : str, Path, Chain or None
        The kinematic model (a robot YAML or a `Chain`); None: none (effects that need the joints
        cannot be tested).
    candidates : tuple of str or None
        The effects to test; None: every effect of the catalogue.
    folds : int
        Cross-validation folds, at least 2.
    seed : int
        Seed of the folds and of the GP fits (same seed, same numbers).
    gp_options : GPOptions or None
        The GP's fit settings; None: the GP's defaults.
    instruments : str, Path or None
        The campaign's instruments YAML, hashed into the provenance.
    inputs : tuple of str or Path
        The input files recorded (hashed) in the provenance.
    auto : bool
        False: one step, the candidates ranked. True: the whole loop (analysis.selection).
    alpha : float
        The family-wise level of each step, in (0, 1).
    min_explained : float
        The smallest explained fraction of held-out variance worth adding, in [0, 1).
    max_steps : int
        The most changes the loop makes, at least 1.
    out : str, Path or None
        Where the loop's final model is saved (only with `auto`).
    exclude_sessions : tuple of str or int
        Sessions (names or numbers) left out of the data.
    reference_session : str, int or None
        The session the session terms are measured from; None: the first.
    session_terms : tuple of str
        The session terms (nuisance effects) of the starting model.
    catalogue : effects.Catalogue or None
        The effects the names refer to and the candidates come from; None: ``effects.default()``.
        It travels with the problem to the worker processes.
    """

    model: HybridModel | str | Path | None = None
    effects: tuple[str, ...] = ()
    gp_inputs: str = "tcp_speed"
    robot: str | Path | Chain | None = None
    candidates: tuple[str, ...] | None = None
    folds: int = 5
    seed: int = 0
    gp_options: GPOptions | None = None
    instruments: str | Path | None = None
    inputs: tuple[str | Path, ...] = ()
    auto: bool = False
    alpha: float = ALPHA
    min_explained: float = 0.02
    max_steps: int = 10
    out: str | Path | None = None
    exclude_sessions: tuple[str | int, ...] = ()
    reference_session: str | int | None = None
    session_terms: tuple[str, ...] = ()
    catalogue: fx.Catalogue | None = None

    def __post_init__(self) -> None:
        # frozen: the normalised tuples are set the one way a frozen dataclass allows
        norm = object.__setattr__
        norm(self, "effects", _names("effects", self.effects))
        norm(self, "session_terms", _names("session_terms", self.session_terms))
        if self.candidates is not None:
            norm(self, "candidates", _names("candidates", self.candidates))
        for field in ("inputs", "exclude_sessions"):
            value = getattr(self, field)
            if isinstance(value, (str, Path)) or not isinstance(value, Sequence):
                raise _fail(field, value, "a sequence (a list or a tuple)")
            norm(self, field, tuple(value))
        if self.gp_inputs not in GP_INPUTS:
            raise _fail("gp_inputs", self.gp_inputs, f"one of {', '.join(GP_INPUTS)}")
        if not isinstance(self.model, (HybridModel, str, Path, type(None))):
            raise _fail("model", self.model, "a HybridModel, a saved model's directory or None")
        if not isinstance(self.robot, (str, Path, Chain, type(None))):
            raise _fail("robot", self.robot, "a robot YAML's path, a Chain or None")
        for field, low in (("folds", 2), ("max_steps", 1), ("seed", 0)):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise _fail(field, value, f"an integer >= {low}")
        if not isinstance(self.alpha, (int, float)) or not 0 < self.alpha < 1:
            raise _fail("alpha", self.alpha, "a fraction in (0, 1)")
        if not isinstance(self.min_explained, (int, float)) or not 0 <= self.min_explained < 1:
            raise _fail("min_explained", self.min_explained, "a fraction in [0, 1)")
        if not isinstance(self.auto, bool):
            raise _fail("auto", self.auto, "True or False")
        if self.gp_options is not None and not isinstance(self.gp_options, GPOptions):
            raise _fail("gp_options", self.gp_options, "a GPOptions or None")
        if self.catalogue is not None and not isinstance(self.catalogue, fx.Catalogue):
            raise _fail("catalogue", self.catalogue, "an effects.Catalogue or None")
        if self.out is not None and not self.auto:
            raise _fail("out", self.out, "None without auto (it saves the final model of the loop; fit a model "
                        "with dt fit)")
