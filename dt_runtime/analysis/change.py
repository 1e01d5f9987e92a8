"""One change of a model in `dt diagnose --auto` (analysis.selection): an effect added or removed,
the GP moved to other inputs, a session term added. Typed inside the code; the results and the
reports show its label ("+backlash", "-thermal", "GP -> joints", "+session tool"), the strings
of the `change` and `added` keys (docs/cli.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, cast

__all__ = ["KINDS", "Change"]

Kind = Literal["effect", "remove", "gp_inputs", "session"]
KINDS: tuple[Kind, ...] = ("effect", "remove", "gp_inputs", "session")

# the label of each kind: the one place a change becomes text, and the text a change is read from
_PREFIX: dict[str, str] = {"effect": "+", "remove": "-", "gp_inputs": "GP -> ", "session": "+session "}


@dataclass(frozen=True)
class Change:
    """One change of a model.

    Parameters
    ----------
    kind : {"effect", "remove", "gp_inputs", "session"}
        An effect added, an effect removed (the backward pass), the GP on other inputs, a session
        term added.
    name : str
        The effect, the GP's inputs (``GP_INPUTS``) or the session term.
    """

    kind: Kind
    name: str

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Change.kind: {self.kind!r} is not allowed; one of {', '.join(KINDS)}")
        if not self.name:
            raise ValueError("Change.name: an empty name is not allowed")

    def label(self) -> str:
        """The change as the results and the reports print it, e.g. "+backlash", "GP -> joints"."""
        return _PREFIX[self.kind] + self.name

    def __str__(self) -> str:
        return self.label()

    @property
    def adds(self) -> bool:
        """Whether the change adds a term (an effect or a session term)."""
        return self.kind in ("effect", "session")

    @classmethod
    def parse(cls, label: str) -> Change:
        """The change a label names (`label` of a change: a saved diagnose.json's `change` and
        `added`); ValueError for any other text.

        Parameters
        ----------
        label : str
            The label.

        Returns
        -------
        Change
        """
        # the longest prefixes first: "+session tool" is a session term, not the effect "session tool"
        for kind in sorted(_PREFIX, key=lambda k: -len(_PREFIX[k])):
            if label.startswith(_PREFIX[kind]) and len(label) > len(_PREFIX[kind]):
                return cls(cast(Kind, kind), label[len(_PREFIX[kind]):])
        raise ValueError(f"{label!r} is not a change's label; e.g. +backlash, -thermal, GP -> joints, "
                         "+session tool")
