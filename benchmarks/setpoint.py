"""`python -m benchmarks.setpoint [--json]`: the per-set-point cost of a corrected path at the
controller's rate, against the correction law written plainly, measured in the same run.

A weld seam (lines and an arc, 250 mm/s, `dt correct --path`'s format) interpolated at --rate Hz;
on every set-point, CPU time (time.process_time, one BLAS thread) per call of
- the inverse kinematics: `frames.newton_ik` warm-started from the previous set-point's joints
  (its compiled kernel, `frames.ik_kernel`, when numba is there), the same on plain floats
  (`floats`: the code before the kernel) and `Chain.ik` from the same seed (the baseline);
- the whole correction (GP mean + std, the effect terms, the IK where the map reads joints, Eq. 11's
  U and the volume flag): `twin.corrector.Corrector` (the one law every correction runs through)
  vs the law written plainly (tests/support/reference_correction.py: the map's own Inputs,
  `Chain.ik`, the labelled Eq. 11 budget) under the same conditions (the baseline), the largest
  difference of their commands and of their U (mm), and the law's numpy path warm-started
  (`numpy_warm`, `Corrector(compiled=False)`: the code before the compiled kernel);
on the quick demo's twin (the paper's map: GP of TCP and speed) and on the same campaign calibrated
with the geometric effect (a joint-space map). The twins are trained into a temporary directory
(~1 min) unless --twin / --geometric-twin name them.

Keys: `rate_hz`, `n_setpoints`, `ik_us` {`warm`, `floats`, `baseline`: {`mean`, `p99`}, `compiled`,
`speedup`, `speedup_vs_floats`, `max_joint_diff_rad`, `max_joint_diff_floats_rad`, `mean_steps`},
`twins` {`demo`, `geometric`: {`needs`, `compiled`, `correction_us` {`fast`, `warm` (the fixed point
started from the previous set-point's correction, as the streaming loop and `dt correct --path`
do), `numpy_warm`, `baseline`: {`mean`, `p99`}, `speedup`, `speedup_warm`, `speedup_vs_numpy`},
`max_diff_mm`, `max_diff_U_mm`, `max_diff_warm_mm`, `max_diff_warm_U_mm`, `max_diff_numpy_warm_mm`}}, `targets_us` {`ik`: 50, `correction`: 100}, `machine` (the reference
workload's time, load, CPU: `benchmarks._common.Machine`), `relative` (each p99 divided by the
reference workload's time). `--load-core`: while another process keeps one core busy.
"""
from __future__ import annotations

import contextlib
import io
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import Machine, busy_core, cli, emit

SEAM = """path: 1
start: [900, 0, 550]
speed: 250
acceleration: 2000
joints: [0.0, 0.0959, 0.9323, 0.0, -0.4282, 0.0]
segments:
  - line: {to: [950, 0, 550]}
  - arc: {via: [985.35533906, 14.64466094, 550], to: [1000, 50, 550]}
  - line: {to: [1000, 120, 550], speed: 100}
  - line: {to: [1000, 120, 600]}
"""
TARGETS_US = {"ik": 50, "correction": 100}


def _stats(us: list[float]) -> dict:
    a = np.asarray(us)
    return {"mean": round(float(a.mean()), 1), "p99": round(float(np.percentile(a, 99)), 1)}


def _timed(fn, args: list[tuple]) -> tuple[list, list[float]]:
    """fn(*a) for every a, each call's CPU time (us)."""
    out, us = [], []
    clock = time.process_time
    for a in args:
        t0 = clock()
        r = fn(*a)
        us.append((clock() - t0) * 1e6)
        out.append(r)
    return out, us


def twins(tmp: Path) -> tuple[Path, Path]:
    """The quick demo's twin and its campaign calibrated with the geometric effect."""
    from dt_runtime.cli.main import main
    from dt_runtime.workflows.demo import run_demo

    with contextlib.redirect_stdout(io.StringIO()):
        run_demo(tmp / "demo", quick=True)
        rc = main(["calibrate", "--campaign", str(tmp / "demo" / "campaign"), "--effects", "geometric",
                   "--out", str(tmp / "geometric"), "--no-progress"])
    if rc not in (0, 3):  # 3: a validity warning of the quick plan
        raise SystemExit(f"dt calibrate --effects geometric failed ({rc})")
    return tmp / "demo" / "model", tmp / "geometric"


def _setpoints(rate: float, tmp: Path):
    from dt_runtime.programs.path import interpolate, read_path

    (tmp / "seam.yaml").write_text(SEAM)
    path = read_path(tmp / "seam.yaml")
    return path, interpolate(path, rate)


def _ik(chain, path, sp) -> dict:
    from dt_runtime.frames.newton_ik import NewtonIK

    ik, floats = NewtonIK(chain), NewtonIK(chain, compiled=False)
    q_prev = [path.joints]
    for x in sp.p:  # the seeds: the previous set-point's joints
        q_prev.append(chain.ik(x, q_prev[-1]))
    args = list(zip(sp.p, q_prev[:-1]))
    steps = []

    def warm(x, q):
        r = ik.solve(x, q)
        steps.append(ik.iterations)
        return r

    got, us_warm = _timed(warm, args)
    got_f, us_floats = _timed(floats.solve, args)
    ref, us_base = _timed(chain.ik, args)
    w, f, b = _stats(us_warm), _stats(us_floats), _stats(us_base)
    return {"warm": w, "floats": f, "baseline": b, "compiled": ik._k is not None,
            "speedup": round(b["mean"] / w["mean"], 1), "speedup_vs_floats": round(f["mean"] / w["mean"], 1),
            "max_joint_diff_rad": float(np.max(np.abs(np.array(got) - np.array(ref)))),
            "max_joint_diff_floats_rad": float(np.max(np.abs(np.array(got) - np.array(got_f)))),
            "mean_steps": round(float(np.mean(steps)), 2)}


def _correction(twin_dir: Path, path, sp) -> dict:
    from dt_runtime.twin.conditions import Conditions
    from dt_runtime.twin.corrector import Corrector
    from dt_runtime.twin.twin import Twin
    from tests.support.reference_correction import ReferenceCorrector

    twin, fast = Twin.load(twin_dir), Corrector(Twin.load(twin_dir))
    joints = "joints" in twin.needs
    conds, got, us_fast = [], [], []
    q, prev = (path.joints if joints else None), None
    clock = time.process_time
    for k in range(sp.n):  # the path's chain of conditions: the arm stands at the previous command
        cond = Conditions(joints=q, previous=prev)
        t0 = clock()
        r = fast.correct(sp.p[k], float(sp.programmed[k]), cond)
        us_fast.append((clock() - t0) * 1e6)
        conds.append(cond)
        got.append(r)
        q, prev = (r.joints if joints else None), r.command
    # warm: the fixed point started from the previous set-point's correction (what the loop does)
    warm_fast = Corrector(Twin.load(twin_dir))
    warm_args = [(sp.p[k], float(sp.programmed[k]), conds[k], None if k == 0 else got[k - 1].command - sp.p[k - 1])
                 for k in range(sp.n)]
    warm, us_warm = _timed(warm_fast.correct, warm_args)
    # the numpy path (the law before its compiled kernel), warm-started as the loop does
    numpy_warm, us_numpy = _timed(Corrector(Twin.load(twin_dir), compiled=False).correct, warm_args)
    ref, us_base = _timed(ReferenceCorrector(twin).correct, [(sp.p[k], float(sp.programmed[k]), conds[k]) for k in range(sp.n)])
    f, w, nw, b = _stats(us_fast), _stats(us_warm), _stats(us_numpy), _stats(us_base)

    def dmax(xs, ys, key):
        return float(max(np.abs(getattr(g, key) - getattr(r, key)).max() for g, r in zip(xs, ys)) * 1e3)

    return {"needs": list(twin.needs), "compiled": fast.compiled,
            "correction_us": {"fast": f, "warm": w, "numpy_warm": nw, "baseline": b,
                              "speedup": round(b["mean"] / f["mean"], 1),
                              "speedup_warm": round(b["mean"] / w["mean"], 1),
                              "speedup_vs_numpy": round(nw["mean"] / w["mean"], 1)},
            "max_diff_mm": dmax(got, ref, "command"), "max_diff_U_mm": dmax(got, ref, "U"),
            "max_diff_warm_mm": dmax(warm, ref, "command"), "max_diff_warm_U_mm": dmax(warm, ref, "U"),
            "max_diff_numpy_warm_mm": dmax(warm, numpy_warm, "command")}


def run(rate: float = 500.0, twin: str = "", geometric_twin: str = "") -> dict:
    from dt_runtime.twin.twin import Twin

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        demo, geo = (Path(twin), Path(geometric_twin)) if twin and geometric_twin else twins(tmp)
        path, sp = _setpoints(rate, tmp)
        chain = Twin.load(geo).e_lt.chain()
        return {"rate_hz": rate, "n_setpoints": sp.n, "robot": chain.name, "ik_us": _ik(chain, path, sp),
                "twins": {"demo": _correction(demo, path, sp), "geometric": _correction(geo, path, sp)},
                "targets_us": TARGETS_US}


def main() -> None:
    args = cli(__doc__, rate=500.0, twin="", geometric_twin="", load_core=False)
    with busy_core(args.load_core) as loaded, Machine() as m:
        res = run(args.rate, args.twin, args.geometric_twin)
    res["machine"] = m.report() | {"one_core_loaded": loaded}
    rel = {f"ik_{k}_p99": res["ik_us"][k]["p99"] * 1e-6 for k in ("warm", "floats", "baseline")}
    for name, t in res["twins"].items():
        for k in ("fast", "warm", "numpy_warm", "baseline"):
            rel[f"correction_{name}_{k}_p99"] = t["correction_us"][k]["p99"] * 1e-6
    res["relative"] = m.relative(times_s=rel)
    if args.json:
        emit(res, True, "")
        return
    ik = res["ik_us"]
    print(f"set-point correction at {res['rate_hz']:g} Hz, {res['n_setpoints']} set-points (CPU time per call)")
    print(f"  IK ({res['robot']}): warm Newton {ik['warm']['mean']} us (p99 {ik['warm']['p99']}; on plain floats "
          f"{ik['floats']['mean']} us, p99 {ik['floats']['p99']}), Chain.ik "
          f"{ik['baseline']['mean']} us (p99 {ik['baseline']['p99']}), x{ik['speedup']}, "
          f"{ik['mean_steps']} steps, max |dq| {ik['max_joint_diff_rad']:.1e} rad; target <= {TARGETS_US['ik']} us")
    for name, t in res["twins"].items():
        c = t["correction_us"]
        print(f"  correction, {name} twin (needs {', '.join(t['needs']) or 'nothing'}): fast {c['fast']['mean']} us "
              f"(p99 {c['fast']['p99']}), warm-started {c['warm']['mean']} us (p99 {c['warm']['p99']}; numpy path "
              f"{c['numpy_warm']['mean']} us, p99 {c['numpy_warm']['p99']}), "
              f"plain law {c['baseline']['mean']} us (p99 {c['baseline']['p99']}), "
              f"x{c['speedup']}, max difference {t['max_diff_mm']:.1e} mm (U {t['max_diff_U_mm']:.1e} mm); target <= {TARGETS_US['correction']} us")
    mc = res["machine"]
    print(f"  machine: reference workload {mc['reference_s']} s (speed {mc['speed']}), load {mc['load']['start']} -> "
          f"{mc['load']['end']}{', one core kept busy' if mc['one_core_loaded'] else ''}")


if __name__ == "__main__":
    main()
