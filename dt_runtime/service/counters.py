"""The daemon's counters: one object, read by `.../health` (the bus), by the summary (the JSON of
`dt run` and `dt status`) and by the operator's status line, so the three never disagree.

Totals since the start (`ticks`, `failures`, ...) and runs "in a row" (reset when a command goes
through again, or a reading is tested) that make the status `degraded` while they last; the
last problem seen, in words; the time of the last tick; since when no camera reading was tested.
Written by the loop only (no lock: the housekeeping thread reads numbers, never a half-done
update that matters).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any


@dataclass
class Counters:
    """The daemon's counters (the comments say what each counts); daemon times in s, `last_tick_wall`
    epoch s, `last_tick_mono` the host's monotonic clock (the watchdog's)."""

    ticks: int = 0  # commands sent (moved): points of a program, set-points of a path
    failures: int = 0  # Eq. 17 tests failed
    refused: int = 0  # commands the correction refused (the robot not moved)
    driver_faults: int = 0
    stale_measurements: int = 0  # MVS readings older than max_measurement_age_s: refused, not tested
    mvs_refused: int = 0  # MVS readings refused by the camera driver (lost, late, untracked, ...)
    uncorrected: int = 0  # commands sent without the correction (it was not trusted)
    refused_in_row: int = 0
    driver_faults_in_row: int = 0
    mvs_refused_in_row: int = 0
    last_problem: str | None = None
    camera_refused_since: float | None = None  # daemon time of the first untested reading in a row
    last_tick_wall: float | None = None
    last_tick_mono: float = float("-inf")  # the watchdog is fed from READY on

    def in_trouble(self) -> bool:
        """A run of refusals or faults is going on: the status is degraded while it lasts."""
        return bool(self.refused_in_row or self.driver_faults_in_row or self.mvs_refused_in_row)

    def ticked(self, n: int = 1) -> None:
        """Count commands sent and note the tick's time (wall and monotonic).

        Parameters
        ----------
        n : int
            Commands (set-points of a path) sent.
        """
        self.ticks += n
        self.last_tick_wall, self.last_tick_mono = time.time(), time.monotonic()

    def summary(self) -> dict[str, Any]:
        """The counters' keys of the summary (`dt run --json`, `dt status`)."""
        return {"ticks": self.ticks, "t_test_failures": self.failures, "refused_commands": self.refused,
                "driver_faults": self.driver_faults, "uncorrected_commands": self.uncorrected,
                "stale_measurements": self.stale_measurements, "mvs_refused": self.mvs_refused}

    def health(self, now: float) -> dict[str, Any]:
        """The counters' keys of `.../health`.

        Parameters
        ----------
        now : float
            Daemon time, s (for `camera_untested_s`).

        Returns
        -------
        dict
            `last_tick`, `ticks`, `refused_in_row`, `driver_faults_in_row`, `stale_measurements`,
            `mvs_refused`, `mvs_refused_in_row`, `camera_untested_s`.
        """
        return {"last_tick": self.last_tick_wall, "ticks": self.ticks, "refused_in_row": self.refused_in_row,
                "driver_faults_in_row": self.driver_faults_in_row, "stale_measurements": self.stale_measurements,
                "mvs_refused": self.mvs_refused, "mvs_refused_in_row": self.mvs_refused_in_row,
                "camera_untested_s": (None if self.camera_refused_since is None
                                      else round(now - self.camera_refused_since, 3))}
