"""The camera frame's re-referencing in service: an offered rigid shift (`Escalator.shift`, the
failing Eq. 17 readings fitted as one small rotation and translation of the camera set-up)
applied to the twin's T_mvs, and kept across restarts in the store's resume row.

docs/service.md ("Re-referencing instead of paging").
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dt_runtime.frames.registration import RigidTransform
from dt_runtime.twin.twin import Twin

log = logging.getLogger("dt.run")


def correction_of(offer: dict[str, Any]) -> RigidTransform:
    """The transform of GL that takes a shifted camera's points back: the readings came out as
    q + omega x q + dt (omega: `rotation_mrad`, dt: `translation_mm`), so q' = exp(-[omega]x) q - dt
    (to first order in the small rotation, as the fit).

    Parameters
    ----------
    offer : dict
        An offer (`Escalator.shift`): `rotation_mrad`, `translation_mm`.

    Returns
    -------
    RigidTransform
    """
    omega = np.asarray(offer["rotation_mrad"], dtype=float) * 1e-3
    dt = np.asarray(offer["translation_mm"], dtype=float) * 1e-3
    return RigidTransform(Rotation.from_rotvec(-omega).as_matrix(), -dt)


class MvsFrame:
    """The twin's camera frame T_mvs as calibrated (`base`) and as re-referenced in service.

    Parameters
    ----------
    twin : Twin
        The daemon's twin; its `T_mvs` is replaced in place (the monitor reads it every test).
    """

    def __init__(self, twin: Twin):
        self.twin, self.base = twin, twin.T_mvs
        self.count = 0  # re-referencings applied on top of the twin's frame

    def apply(self, offer: dict[str, Any]) -> Callable[[], None]:
        """Apply an offer's shift on top of the current frame; returns the undo.

        Parameters
        ----------
        offer : dict
            The open offer (`Escalator.offer`).

        Returns
        -------
        callable
            Puts the frame back as it was.
        """
        before, count = self.twin.T_mvs, self.count
        self.twin.T_mvs = correction_of(offer).compose(before)
        self.count += 1
        log.warning("camera frame re-referenced: %s mm, %s mrad", offer["translation_mm"], offer["rotation_mrad"])

        def undo() -> None:
            self.twin.T_mvs, self.count = before, count
        return undo

    def jacobian(self) -> Callable[[np.ndarray], np.ndarray] | None:
        """The arm's position Jacobian in GL axes from the twin's robot config (`escalation.Jacobian`),
        or None when the twin has none (then no re-referencing is offered: the arm is not ruled out).

        Returns
        -------
        callable or None
        """
        chain = self.twin.e_lt.chain() or self.twin.e_mvs_lt.chain()
        if chain is None:
            return None
        R = self.twin.T_rdk.R  # robot axes -> GL axes

        def jac(q: np.ndarray) -> np.ndarray:
            return np.einsum("ab,nbj->naj", R, chain.jacobian(np.asarray(q, dtype=float)))
        return jac

    def to_dict(self) -> dict[str, Any]:
        """What the resume row carries under `mvs_rereferenced` ({} before any re-referencing)."""
        if not self.count:
            return {}
        return {"mvs_rereferenced": {"base": self.base.matrix.tolist(), "T_mvs": self.twin.T_mvs.matrix.tolist(),
                                     "count": self.count}}

    def restore(self, saved: dict[str, Any] | None) -> None:
        """Take up a re-referencing the store kept, if it was made on this twin's frame (a twin
        calibrated anew starts from its own).

        Parameters
        ----------
        saved : dict or None
            The resume row's `mvs_rereferenced`.
        """
        if not saved:
            return
        if not np.allclose(np.asarray(saved["base"], dtype=float), self.base.matrix, atol=1e-12):
            log.warning("the store's camera re-referencing was made on another twin's frame: not taken up")
            return
        self.twin.T_mvs = RigidTransform.from_matrix(np.asarray(saved["T_mvs"], dtype=float))
        self.count = int(saved.get("count", 1))
        log.info("camera frame re-referenced %d time(s) in service: taken up from the store", self.count)
