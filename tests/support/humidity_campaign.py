"""A campaign with an error outside the catalogue (issue 13, part 4b; docs/diagnosis.md, "Effects of your own"):
the UR10 generator's clean arm (tests/support/ur10_generator.py: geometric errors, 15 um tracker noise per
axis, 40 points x 3 passes) with two logged columns of the file's own, `humidity` (%, a slow
random walk over the campaign) moving the TCP by K_HUMIDITY m/%, and `fixture_temp` (deg C),
which turns joints 2 and 3 by K_FIXTURE rad/K when `fixture` is set.

    python -m tests.support.humidity_campaign --out out/humidity.csv
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dt_runtime.measurements.dataset import write_table
from tests.support.ur10_generator import fk, generate

K_HUMIDITY = np.array([6e-6, -4e-6, 5e-6])  # m/% along x, y, z: 0.06, -0.04, 0.05 mm per 10 %
K_FIXTURE = {2: 2e-5, 3: -1.5e-5}  # rad/K: joints 2 and 3 turn with the fixture's temperature


def campaign(path: str | Path, k_humidity=K_HUMIDITY, fixture: bool = False, seed: int = 3) -> Path:
    """Write the contract CSV with the two columns of the file's own; returns the path."""
    path = Path(path)
    ds = generate("none", seed=seed, n_points=40, passes=3)
    rng = np.random.default_rng(100 + seed)
    h = 45 + np.cumsum(rng.normal(0, 3.0, ds.n))  # one reading per row, a slow random walk
    tf = 20 + 5 * np.sin(np.arange(ds.n) / 17.0) + rng.normal(0, 1, ds.n)
    ds.error = ds.error + np.outer(h - 45, k_humidity)
    if fixture:
        dq = np.zeros_like(ds.joints)
        for j, c in K_FIXTURE.items():
            dq[:, j - 1] = c * (tf - 20)
        ds.error = ds.error - (fk(ds.joints + dq) - fk(ds.joints))  # e = commanded - measured
    ds.measured = None  # the error columns carry it
    write_table(ds, path)  # the contract's columns; the file's own are appended below
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0] + ",humidity,fixture_temp"]
                              + [f"{line},{a:.4f},{b:.4f}" for line, a, b in zip(lines[1:], h, tf)]) + "\n")
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="FILE.csv")
    p.add_argument("--fixture", action="store_true", help="also the fixture's temperature turning joints 2 and 3")
    p.add_argument("--seed", type=int, default=3)
    a = p.parse_args()
    print(campaign(a.out, fixture=a.fixture, seed=a.seed))


if __name__ == "__main__":
    main()
