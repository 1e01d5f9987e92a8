"""Long soak and fault runs: `python -m pytest -m soak` (the default suite runs the short
versions in tests/integration/test_runtime.py)."""
import pytest


@pytest.mark.soak
def test_a_simulated_day_without_false_requests_and_every_fault_detected():
    from benchmarks.soak import soak

    r = soak(hours=24.0, fault_hours=2.0)
    assert r["fault_free"]["requests"] == 0  # target < 0.1 per day
    assert all(v is not None for v in r["detection_delay_s"].values()), r["detection_delay_s"]
