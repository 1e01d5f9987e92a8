"""Smoke run of `python -m benchmarks.fit_scale` on a small row subset of UR10 Series A (the full
run takes minutes): `dt fit` in a subprocess, exact vs sparse GP held out, the contract keys."""
import math

import pytest

from benchmarks.fit_scale import run


def test_fit_scale_smoke():
    r = run(n_big=700, n_cmp=300, n_inducing=100, models=("paper",))
    for k in ("n_train", "seconds", "peak_rss_gb", "rmse_ratio_vs_exact", "n_inducing", "paper_seconds",
              "paper_exact_rms_mm", "paper_sparse_rms_mm", "paper_heldout_rms_mm", "heldout_asis_rms_mm",
              "exact_seconds_at_n_compare", "exact_est_seconds_at_n_train"):
        assert k in r, k
    assert r["n_train"] == 700 and r["n_compare"] == 300 and r["n_inducing"] == 100
    for k, v in r.items():
        if isinstance(v, float):
            assert math.isfinite(v), (k, v)
    assert 0 < r["seconds"] and 0 < r["peak_rss_gb"] < 4
    assert r["rmse_ratio_vs_exact"] < 1.2
    # the GP learns something the as-is error does not have
    assert r["paper_heldout_rms_mm"] < r["heldout_asis_rms_mm"]


def test_fit_rows_bounded_memory_small():
    """`python -m benchmarks.fit_scale --rows N` at 10^5 rows: `dt fit` in a subprocess, its peak
    RSS far below the 2 GB budget of 10^6 rows (the sparse GP works in bounded chunks)."""
    from benchmarks.fit_scale import run_rows

    r = run_rows(100_000, n_small=5_000, n_cmp=300, n_test=500)
    assert r["n_train"] == 100_000 and r["n_small"] == 5_000
    for k in ("seconds", "peak_rss_gb", "rmse_ratio_vs_exact", "seconds_ratio_vs_small", "rss_ratio_vs_small"):
        assert math.isfinite(r[k]) and r[k] > 0, k
    assert r["peak_rss_gb"] < 1.0 and r["within_budget"]
    assert r["heldout_rms_mm"] < 0.01  # the error field's 0.3-0.8 mm, learned to the 0.01 mm noise


@pytest.mark.soak
def test_fit_rows_million_under_2_gb():
    from benchmarks.fit_scale import run_rows

    r = run_rows(1_000_000)
    assert r["peak_rss_gb"] < 2.0 and r["heldout_rms_mm"] < 0.01
