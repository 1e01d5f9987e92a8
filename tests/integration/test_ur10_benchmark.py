"""`python -m benchmarks.ur10` on Series D (the smallest, ~1 min): the diagnose loop beats the
paper's model on real data, every figure held out. Behind the soak marker (the full run over
A-D takes ~15 min)."""
import pytest

from benchmarks.ur10 import run


@pytest.mark.soak
def test_ur10_loop_beats_the_paper_model_on_series_d():
    r = run(("D",))["series"]["D"]
    assert r["n_rows"] == 632
    assert 0.5 < r["registration_rms_mm"] < 1.0
    assert r["final_heldout_mm"] < 0.8 * r["paper_heldout_mm"] < r["as_is_rms_mm"]
    assert "geometric" in r["final_effects"]
