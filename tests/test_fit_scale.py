"""Smoke run of `python -m benchmarks.fit_scale` on a small row subset of UR10 Series A (the full
run takes minutes): `dt fit` in a subprocess, exact vs sparse GP held out, the contract keys."""
import math

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
