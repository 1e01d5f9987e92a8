"""The streaming loop (dt_runtime.service.stream): every set-point corrected once and sent once,
in order, at its time; a refusal ends the stream with its reason; the loop in its own process.
No assertion on timing (the machine is shared): the benchmark measures it (benchmarks.stream)."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.base import WatchdogStop, streams
from dt_kernel.errors import DriverError, TwinError
from dt_runtime.service.stream import StreamProcess, run_stream
from tests.support.stream_fakes import OFFSET, RecordingStreamer, broken_streamer, offset_corrector, recording_streamer


def line(n: int = 200, rate: float = 500.0):
    t = np.arange(n) / rate
    return t, np.column_stack([0.6 + 0.25 * t, 0 * t, 0.5 + 0 * t])  # 250 mm/s along x


@pytest.mark.parametrize("paced", [False, True])
def test_every_set_point_is_corrected_once_and_sent_once_in_order(paced):
    t, p = line()
    calls = []

    def correct(target, tk):
        calls.append(tk)
        return target + OFFSET

    drv = RecordingStreamer()
    assert streams(drv)  # it declares the capability the loop needs (drivers.base.SetpointStreamer)
    # adapt=False: every set-point, however late (a loaded machine would otherwise skip some)
    rep = run_stream(t, p, correct, drv, 500.0, lookahead_s=0.05, gain=500.0, paced=paced, adapt=False)
    assert drv.started == (500.0, 0.05, 500.0) and drv.stopped == 1
    assert calls == list(t)  # each corrected once, in order
    assert [c[1] for c in drv.calls] == list(t)  # each sent once, in order, with its time
    assert np.allclose(np.array([c[0] for c in drv.calls]), p + OFFSET)
    assert rep.n_sent == rep.n_planned == 200 and not rep.stopped
    assert np.allclose(rep.commands, p + OFFSET) and np.all(np.diff(rep.sent_at) >= 0)
    assert rep.correction_us_mean > 0 and np.isfinite(rep.correction_us_p99)
    if paced:  # the sends follow the schedule: 199 periods of 2 ms at the least
        assert np.all(rep.sent_at >= np.arange(200) / 500.0 - 1e-9)  # never before its time (to rounding)
        assert np.isfinite(rep.jitter_p99_ms) and np.isfinite(rep.rate_hz)


def test_a_refused_set_point_ends_the_stream_with_its_reason_and_stops_it():
    t, p = line()
    drv = RecordingStreamer(refuse_at=50)
    rep = run_stream(t, p, offset_corrector(), drv, 500.0, paced=False)
    assert rep.n_sent == 49 and len(drv.calls) == 49 and drv.stopped == 1
    assert rep.stopped == "set-point 50 of 200 refused: protective stop"
    assert rep.commands.shape == (49, 3)


def test_bad_input_is_refused_before_the_stream_starts():
    drv = RecordingStreamer()
    with pytest.raises(TwinError, match="n x 3 targets"):
        run_stream(np.arange(3.0), np.zeros((2, 3)), offset_corrector(), drv, 125.0)
    assert drv.started is None


def test_the_loop_runs_in_its_own_process_and_reports_back():
    t, p = line(100, 125.0)
    sp = StreamProcess(offset_corrector, recording_streamer, t, p, 125.0, rt_priority=0)
    rep = sp.result(timeout=60)
    assert rep.n_sent == 100 and not rep.stopped and sp.sent == 100
    assert np.allclose(rep.commands, p + OFFSET) and rep.realtime is False
    bad = StreamProcess(offset_corrector, broken_streamer, t, p, 125.0, rt_priority=0)
    with pytest.raises(TwinError, match="DriverError: no controller at 127.0.0.1:30004"):
        bad.result(timeout=60)


class _SlowOnce(RecordingStreamer):
    """Stalls once, at set-point `at` (1-based), for `stall_s`: a host that stopped scheduling the loop."""

    def __init__(self, at: int, stall_s: float):
        super().__init__()
        self.at, self.stall_s = at, stall_s

    def stream(self, target, t: float) -> None:
        super().stream(target, t)
        if len(self.calls) == self.at:
            import time

            time.sleep(self.stall_s)


def test_a_stalled_tick_makes_the_path_wait_not_jump():
    """A stall of 25 periods after set-point 20: the next set-point is sent late and the schedule
    moves on by the delay (the path waits there), named in `degraded`; every set-point is passed."""
    t, p = line(100, 500.0)
    drv = _SlowOnce(20, 0.05)
    rep = run_stream(t, p, offset_corrector(), drv, 500.0)
    assert rep.n_sent == 100 and not rep.stopped and len(drv.calls) + rep.skipped == 100
    assert rep.pauses >= 1 and rep.pause_max_ms >= 40.0  # at least the stall less the 2-period allowance
    assert "the path waited" in rep.degraded and "not scheduled" in rep.degraded  # (a loaded host: more waits)


def test_a_host_slower_than_the_rate_skips_set_points_and_keeps_the_path_on_time():
    """A correction of 3 periods (a sleep: at least that long): the loop sends the set-point due
    when its work is done, so the path keeps its time at a lower rate; the last set-point is
    sent; `degraded` names the skipping and its cause."""
    import time

    t, p = line(120, 500.0)

    def slow(target, tk):
        time.sleep(3 / 500.0)
        return target + OFFSET

    drv = RecordingStreamer()
    rep = run_stream(t, p, slow, drv, 500.0)
    sent_t = [c[1] for c in drv.calls]
    assert rep.n_sent == 120 and not rep.stopped and sent_t[-1] == t[-1]  # to the end
    assert rep.skipped > 0 and len(drv.calls) == 120 - rep.skipped
    assert sent_t == sorted(set(sent_t))  # in order, none twice
    assert np.isnan(rep.commands).any(axis=1).sum() == rep.skipped
    assert "skipped" in rep.degraded and "longer than the 2 ms period" in rep.degraded


class _RefusesAfterStall(_SlowOnce):
    """Stalls after set-point 10, then refuses the next with `error` (the watchdog, or a fault of the cell)."""

    def __init__(self, error):
        super().__init__(10, 0.05)
        self.error = error

    def stream(self, target, t: float) -> None:
        if len(self.calls) == 10:
            raise self.error
        super().stream(target, t)


@pytest.mark.parametrize("error,host", [(WatchdogStop("the controller's watchdog stopped the arm"), True),
                                        (DriverError("protective stop"), False),
                                        (DriverError("the RTDE connection is down"), False)])
def test_only_the_controllers_watchdog_after_a_stall_is_put_down_to_the_host(error, host):
    """A refusal right after a stall: the watchdog's is the host's (`host_stalled`, the stall named);
    a protective stop or a dropped connection is the cell's, whatever came before it."""
    t, p = line(100, 500.0)
    rep = run_stream(t, p, offset_corrector(), _RefusesAfterStall(error), 500.0)
    assert rep.n_sent == 10 and rep.stopped.startswith("set-point 11 of 100 refused")
    assert rep.host_stalled is host
    assert ("not been scheduled" in rep.stopped) is host


def _no_corrector():
    raise ValueError("the twin would not load")


def test_a_child_whose_daemon_is_gone_says_so_in_one_line_without_a_traceback(capfd):
    # the daemon killed: its end of the pipe closed; every send of the child raised BrokenPipeError
    # and the child died with a traceback of two exceptions
    import multiprocessing as mp

    from dt_runtime.service import stream

    recv, send = mp.Pipe(duplex=False)
    recv.close()
    stream._child(send, None, None, None, None, None, _no_corrector, None, None, None, 100.0, 0.1, 300.0, None, True)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "BrokenPipe" not in err
    assert err.count("\n") == 1 and "the daemon is gone" in err and "the twin would not load" in err
