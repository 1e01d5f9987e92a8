"""The raw measurements of one phase of a calibration campaign (registration, DOE, validation),
as the campaign runner collects them through the drivers and as the campaign files hold them
(`measurements.campaign_files`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PhaseData:
    """Raw measurements of one phase; positions in metres, NaN where an instrument refused."""

    phase: str
    point_id: np.ndarray
    rep: np.ndarray
    target: np.ndarray  # commanded target, robot frame
    speed: np.ndarray  # m/s
    p_rdk: np.ndarray  # controller TCP, robot frame
    p_lt: np.ndarray  # tracker frame
    p_mvs: np.ndarray  # MVS frame
    t: np.ndarray
    q: np.ndarray
    temperature: np.ndarray
    payload: np.ndarray
    truth_lt: np.ndarray | None = None  # noise-free truth in the tracker frame (simulation only)
    axis: np.ndarray | None = None
    distance: np.ndarray | None = None
    refusals: list[str] = field(default_factory=list)

    @property
    def n(self) -> int:
        """Number of rows."""
        return len(self.point_id)

    def rows(self, mask: np.ndarray) -> PhaseData:
        """The phase's rows where `mask` is true (its refusals kept whole).

        Parameters
        ----------
        mask : ndarray
            (n,) bool.

        Returns
        -------
        PhaseData
        """
        def cut(a):
            return None if a is None else np.asarray(a)[mask]

        return PhaseData(self.phase, cut(self.point_id), cut(self.rep), cut(self.target), cut(self.speed),
                         cut(self.p_rdk), cut(self.p_lt), cut(self.p_mvs), cut(self.t), cut(self.q),
                         cut(self.temperature), cut(self.payload), cut(self.truth_lt), cut(self.axis),
                         cut(self.distance), list(self.refusals))
