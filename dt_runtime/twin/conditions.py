"""What a twin's error maps read beside the command, at the moment it is corrected.

The paper's map reads only the commanded TCP and speed. A map with physical effect terms reads
more (`HybridModel.needs`): the joint angles of the command (the nominal inverse kinematics of
the robot config, started from where the controller says the arm stands), the temperature and
payload (a sensor driver or the program), the time (the campaign's time base, for drift) and
the direction of approach (the previous command: backlash and dynamic). `command_inputs` turns a
command and its `Conditions` into the rows the map's regressors need: the previous command as
history, then the command itself.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects import Inputs

# Condition -> where a cell gets it (the error message of a missing one says so).
SOURCES = {"temperature": "a temperature sensor (drivers) or the program's temperature column",
           "payload": "the program's payload column or the robot controller",
           "t": "the clock (the campaign's time base)",
           "joints": "the robot controller's joint angles (the inverse kinematics starts there)"}


@dataclass(frozen=True)
class Conditions:
    """The state of the cell a command is corrected in (SI: deg C, kg, s, rad, m)."""

    temperature: float | None = None
    payload: float | None = None
    t: float | None = None
    joints: np.ndarray | None = None  # where the arm stands now (before this command), rad
    previous: np.ndarray | None = None  # the previous command (robot frame, m); default FK(joints)
    # Other columns the user's declared effects read (humidity, a fixture's temperature), by name.
    extra: dict[str, float] | None = None

    def get(self, name: str):
        """One condition by name: a field of this class or an entry of `extra`.

        Parameters
        ----------
        name : str
            'temperature', 'payload', 't', 'joints', 'previous' or a column of `extra`.

        Returns
        -------
        float, ndarray or None
            None when it is not given.
        """
        if name in ("temperature", "payload", "t", "joints", "previous"):
            return getattr(self, name)
        return None if self.extra is None else self.extra.get(name)


def missing(needs: tuple[str, ...], cond: Conditions | None) -> list[str]:
    """The conditions a map needs that `cond` does not give (speed always comes with the command).

    Parameters
    ----------
    needs : tuple of str
        What the map reads (`HybridModel.needs`).
    cond : Conditions or None
        What the cell gives (None: nothing).

    Returns
    -------
    list of str
        The names needed but not given, in the order of `needs`.
    """
    cond = cond or Conditions()
    return [n for n in needs if n != "speed" and cond.get(n) is None]


def command_inputs(c: np.ndarray, v: float, needs: tuple[str, ...], cond: Conditions | None,
                   chain: Chain | None, q_seed: np.ndarray | None = None,
                   ik: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                   ) -> tuple[Inputs, np.ndarray | None]:
    """The map's input rows for command c at speed v: [previous command, c] (the direction of
    approach) or [c] without history, and the joint angles of c (None if the map needs none).

    Parameters
    ----------
    c : ndarray
        (3,) m, the command (robot frame).
    v : float
        Speed, m/s.
    needs : tuple of str
        What the map reads (`HybridModel.needs`).
    cond : Conditions or None
        The cell's state; its `previous` command (or FK of its `joints`) is the row of history.
    chain : Chain or None
        The robot's nominal kinematics (needed when the map reads joints).
    q_seed : ndarray or None
        (dof,) rad, where the inverse kinematics of c starts (default: the arm's joints now).
    ik : callable or None
        ik(position, q_seed) -> joints (rad); default `chain.ik` (a path's set-points use
        `frames.newton_ik`, the same solution).

    Returns
    -------
    inputs : Inputs
        One or two rows: [previous command, c] or [c].
    q_c : ndarray or None
        (dof,) rad, the joint angles of c; None when the map reads no joints.

    Raises
    ------
    DataError
        A condition the map needs is not given (the message says where a cell gets it), or the
        map needs joints but no robot config (`chain`) is there.
    UnreachableError
        The inverse kinematics finds no joints for c.
    """
    cond = cond or Conditions()
    lack = missing(needs, cond)
    if lack:
        raise DataError("the twin's error map needs " + "; ".join(
            f"{n} (from {SOURCES.get(n, f'the column {n!r} of the program or Conditions.extra')})" for n in lack)
                        + ", which the command's conditions do not give")
    q_now = None if cond.joints is None else np.asarray(cond.joints, dtype=float)
    prev = cond.previous
    if prev is None and q_now is not None and chain is not None:
        prev = chain.fk(q_now)[0]
    rows = [np.asarray(c, dtype=float)] if prev is None else [np.asarray(prev, dtype=float), np.asarray(c, dtype=float)]
    n = len(rows)
    q_c = None
    joints = None
    if "joints" in needs:
        if chain is None:
            raise DataError("the twin's error map needs joint angles but names no robot config")
        assert q_now is not None  # `missing` checked it
        q_c = (ik or chain.ik)(rows[-1], q_now if q_seed is None else q_seed)
        joints = np.vstack([q_now, q_c])[-n:]

    def col(x: float | None) -> np.ndarray | None:
        return None if x is None else np.full(n, float(x))

    extra = {k: np.full(n, float(x)) for k, x in (cond.extra or {}).items()} or None
    return Inputs(commanded=np.vstack(rows), joints=joints, speed=np.full(n, float(v)),
                  temperature=col(cond.temperature), payload=col(cond.payload), t=col(cond.t), extra=extra), q_c
