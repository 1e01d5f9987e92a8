"""Shared bits of the GP benchmarks: the sklearn baseline and output formatting."""
from __future__ import annotations

import argparse
import json
import warnings

import numpy as np


def sklearn_gp(d: int):
    """The baseline: ConstantKernel * RBF(ARD) + WhiteKernel, normalize_y, no optimizer restarts."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    kernel = ConstantKernel(1.0, (1e-5, 1e5)) * RBF(np.ones(d), (1e-3, 1e3)) + WhiteKernel(1e-2, (1e-12, 1e1))
    return GaussianProcessRegressor(kernel, normalize_y=True, n_restarts_optimizer=0, random_state=0)


def fit_sklearn(X, Y, thetas=None):
    """One sklearn GPR per output column (as ours: one model per axis); inputs standardised as ours.
    With `thetas` (our standardised log-hyperparameters) the kernel is fixed, not optimised."""
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    mu, sd = X.mean(0), X.std(0)
    d = X.shape[1]
    models = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for j in range(Y.shape[1]):
            gp = sklearn_gp(d)
            if thetas is not None:
                t = np.asarray(thetas[j])
                gp.set_params(kernel=ConstantKernel(np.exp(t[d])) * RBF(np.exp(t[:d])) + WhiteKernel(np.exp(t[d + 1])),
                              optimizer=None)
            models.append(gp.fit((X - mu) / sd, Y[:, j]))
    return models, mu, sd


def cli(description: str, argv: list[str] | None = None, **options) -> argparse.Namespace:
    """Parse --json and the benchmark's own `options` (name=default, typed by the default); BLAS
    on one thread (or $DT_BLAS_THREADS), as the `dt` command line runs."""
    from dt_runtime.common.threads import limit_blas_threads

    limit_blas_threads()
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    for name, default in options.items():
        p.add_argument(f"--{name.replace('_', '-')}", type=type(default), default=default,
                       help=f"default {default}")
    return p.parse_args(argv)


def emit(res: dict, as_json: bool, title: str) -> None:
    if as_json:
        print(json.dumps(res))
        return
    print(title)
    for k, v in res.items():
        print(f"  {k:<22} {v:.4g}" if isinstance(v, float) else f"  {k:<22} {v}")
