"""Picklable stand-ins for the streaming loop's tests (dt_runtime.service.stream): a streaming
driver that records what it is handed, and a corrector that adds a known offset."""
from __future__ import annotations

import numpy as np

from drivers.base import StreamStatus
from dt_kernel.errors import DriverError

OFFSET = np.array([1e-4, -2e-4, 3e-4])  # m, what the fake corrector adds


class RecordingStreamer:
    """Follows nothing: records each set-point; refuses from set-point `refuse_at` (1-based) on,
    as a controller in protective stop does."""

    def __init__(self, refuse_at: int | None = None):
        self.refuse_at = refuse_at
        self.calls: list[tuple[np.ndarray, float]] = []
        self.started: tuple | None = None
        self.stopped = 0
        self.closed = False

    def start_stream(self, rate_hz: float, lookahead_s: float = 0.1, gain: float = 300.0) -> None:
        self.started = (rate_hz, lookahead_s, gain)

    def stream(self, target, t: float) -> None:
        if self.refuse_at is not None and len(self.calls) + 1 >= self.refuse_at:
            raise DriverError("protective stop")
        self.calls.append((np.array(target, dtype=float), float(t)))

    def stop_stream(self) -> None:
        self.stopped += 1

    def stream_status(self) -> StreamStatus:
        return StreamStatus("streaming" if self.started and not self.stopped else "idle", len(self.calls))

    def close(self) -> None:
        self.closed = True


def offset_corrector():
    return lambda target, t: np.asarray(target, dtype=float) + OFFSET


def recording_streamer():
    return RecordingStreamer()


def broken_streamer():
    raise DriverError("no controller at 127.0.0.1:30004")


def ur_stream_driver(rtde_port: int, script_port: int, rate_hz: float, watchdog_cycles: int):
    """The UR driver, active, against an emulator on loopback, its stream watchdog set."""
    from drivers.ur.driver import UrRtdeController

    drv = UrRtdeController.from_config({
        "host": "127.0.0.1", "rtde_port": rtde_port, "script_port": script_port, "timeout_s": 10.0,
        "frequency_hz": rate_hz, "stream": {"watchdog_cycles": watchdog_cycles}}, source="<stream test>")
    drv.activate()
    return drv
