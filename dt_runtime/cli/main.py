"""The `dt` command line. Every computing command accepts --json and then prints exactly one
JSON object on stdout; logs and progress go to stderr. Errors exit with status 2 and, with
--json, print {"error": ...} so scripts always get one object."""
from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Callable

from dt_kernel.errors import TwinError
from dt_runtime.common.progress import Progress
from dt_runtime.common.threads import limit_blas_threads

log = logging.getLogger("dt")
COMMANDS: dict[str, Callable[[argparse.Namespace], dict]] = {}


def command(name: str):
    def deco(fn):
        COMMANDS[name] = fn
        return fn
    return deco


@command("demo")
def _demo(args: argparse.Namespace) -> dict:
    from dt_runtime.twin.demo import run_demo

    from pathlib import Path

    from dt_runtime.reports.demo_report import write_demo_report  # matplotlib only when reporting

    progress = Progress(enabled=not args.no_progress)
    res = run_demo(args.out, quick=args.quick, seed=args.seed, config=args.config,
                   progress=progress, camera=args.camera)
    report = write_demo_report(res, Path(args.out) / "report.html")
    progress.note(f"wrote {report}")
    return res.summary


@command("simulate")
def _simulate(args: argparse.Namespace) -> dict:
    from dt_runtime.twin.simulate import simulate

    return simulate(args.scenario, args.out, seed=args.seed, progress=_progress(args))


def _effects(text: str | None) -> tuple[str, ...]:
    return tuple(e.strip() for e in text.split(",") if e.strip()) if text else ()


def _progress(args: argparse.Namespace) -> Progress:
    return Progress(enabled=not getattr(args, "no_progress", False))


def _data(args: argparse.Namespace):
    from dt_runtime.analysis.data import load_data

    return load_data(args.data, args.mapping, args.skip_bad)


@command("fit")
def _fit(args: argparse.Namespace) -> dict:
    from dt_runtime.analysis.data import DEFAULT_ROBOT, fit

    return fit(_data(args), _effects(args.effects), args.gp_inputs, args.robot or DEFAULT_ROBOT, args.out,
               seed=args.seed, cv_folds=args.cv, progress=_progress(args))


@command("diagnose")
def _diagnose(args: argparse.Namespace) -> dict:
    from dt_runtime.analysis.data import DEFAULT_ROBOT, run_diagnose

    return run_diagnose(_data(args), args.model, _effects(args.effects), args.gp_inputs,
                        args.robot or DEFAULT_ROBOT, _effects(args.candidates) or None, args.folds,
                        args.seed, progress=_progress(args))


@command("compare")
def _compare(args: argparse.Namespace) -> dict:
    from dt_runtime.analysis.data import floor_of
    from dt_runtime.analysis.compare import compare
    from dt_runtime.reports.compare_report import write_compare_report

    d = _data(args)
    names = _effects(args.names) or None
    result, arrays = compare(args.model, d.dataset, names, noise_floor_m=floor_of(d), cv_folds=args.cv,
                             seed=args.seed, progress=_progress(args))
    result |= {k: v for k, v in d.info.items() if k not in ("n", "data")}
    if args.report:
        result["report"] = str(write_compare_report(result, arrays, args.report))
    return result


@command("run")
def _run(args: argparse.Namespace) -> dict:
    from dt_runtime.service.daemon import run_daemon

    return run_daemon(args.config, args.duration)


@command("status")
def _status(args: argparse.Namespace) -> dict:
    from pathlib import Path

    from dt_runtime.service.store import Store

    if not Path(args.store).exists():
        raise TwinError(f"{args.store}: no such store (start `dt run` first)")
    with Store(args.store) as st:
        return st.last_figures()


def _human(name: str, result: dict) -> str:
    if name == "diagnose":
        lines = [f"held-out 3D RMS of the starting model: {result['rmse_base_mm']:.4f} mm"
                 + (f" (noise floor {result['noise_floor_mm']:.4f} mm)" if result.get("noise_floor_mm") else "")]
        lines += [f"  {r['effect']:<10} explains {100 * r['explained_fraction']:6.1f} %  p = {r['p_value']:.2g}  "
                  f"RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm" for r in result["ranking"]]
        lines += [f"  GP on {r['gp_inputs']:<9} explains {100 * r['explained_fraction']:6.1f} %  p = {r['p_value']:.2g}  "
                  f"RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm"
                  for r in result.get("gp_inputs_ranking", [])]
        return "\n".join(lines + [result["verdict"]])
    if name == "compare":
        lines = [f"{result['n']} rows of {result['dataset']}"
                 + (f"; held out by {result['heldout']['folds']}-fold grouped CV" if result.get("heldout") else "")
                 + (f"; noise floor {result['noise_floor_mm']:.4f} mm" if result.get("noise_floor_mm") else "")]
        for m in result["models"]:
            f = m.get("failures")
            lines.append(f"  {m['name']:<24} 3D RMS {m['rmse_mm']:.4f} mm  mean {m['mae_mm']:.4f}  max {m['max_mm']:.4f}"
                         + (f"  fails Eq. 17: {100 * f['fraction']:.1f} %" if f else ""))
        for c in result.get("worst_cells") or []:
            lines.append(f"  worst: {c['factor']} {c['cell']}: {c['rmse_mm']:.4f} mm ({c['n']} rows)")
        if result.get("report"):
            lines.append(f"report: {result['report']}")
        return "\n".join(lines)
    if name == "fit":
        out = [f"model saved to {result['out']} ({result['n']} rows, {result['fit_seconds']:.1f} s); "
               f"training 3D RMS {result['train_rmse_mm']:.4f} mm"]
        if "heldout_rmse_mm" in result:
            out.append(f"held-out 3D RMS {result['heldout_rmse_mm']:.4f} mm (as is {result['as_is_rmse_mm']:.4f} mm)")
        out += [f"  {p['effect']}.{p['name']} = {p['value']:.6g} +/- {p['u']:.2g} {p['unit']}" for p in result["parameters"]]
        return "\n".join(out)
    if name == "demo":
        s = result
        cov = s["coverage_95"]
        return "\n".join([
            f"precision (Sect. 3.3): {s['precision_before_mm']:.3f} mm -> {s['precision_after_mm']:.3f} mm "
            f"({s['improvement_pct']:.1f} % better; paper: 0.970 -> 0.216 mm, 77.8 %)",
            f"true 3D RMS error at validation targets: {s['true_rms_uncorrected_mm']:.3f} mm uncorrected -> "
            f"{s['true_rms_corrected_mm']:.3f} mm corrected ({s['true_error_reduction_pct']:.1f} % lower)",
            f"coverage of the 95 % expanded uncertainty U(TCP_c): x {cov['x']:.1%}, y {cov['y']:.1%}, z {cov['z']:.1%}",
            f"Eq. 17 t-test pass fraction: {s['t_test_eq17']['pass_fraction_all_axes']:.1%}",
        ])
    return json.dumps(result, indent=2)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dt", description="Traceable digital twin of a collaborative robot arm.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging on stderr")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    d = sub.add_parser("demo", help="the paper's whole experiment on the simulated cell",
                       description="Registration, DOE, GPR, uncertainty budget, validation and t-test "
                                   "on the simulated cell; writes DIR/summary.json and DIR/report.html.")
    d.add_argument("--out", default="out/demo", metavar="DIR", help="output directory (default out/demo)")
    d.add_argument("--quick", action="store_true", help="reduced plan, well under a minute")
    d.add_argument("--seed", type=int, default=None, help="plan seed (default: the plan config's)")
    d.add_argument("--config", default=None, help="demo config YAML (default: configs/demo.yaml)")
    d.add_argument("--camera", default=None, metavar="DRIVER",
                   help="camera driver, overriding the config (sim_images or sim_point)")
    d.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    d.add_argument("--no-progress", action="store_true", help="do not show progress on stderr")

    r = sub.add_parser("run", help="the long-running twin daemon",
                       description="Correct every command, test every MVS measurement (Eq. 17), escalate "
                                   "repeated failures to maintenance over Zenoh; SIGINT/SIGTERM stop cleanly.")
    r.add_argument("--config", required=True, help="runtime YAML (see configs/runtime.yaml)")
    r.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    r.add_argument("--json", action="store_true", help="print the run summary as one JSON object")

    sm = sub.add_parser("simulate", help="measurement data from the simulated cell",
                        description="Run a scenario's experiment plan on the simulated cell (tracker registered by "
                                    "the three-line method) and write the measurement table (DESIGN.md) as CSV, "
                                    "with FILE.csv.meta.json: scenario, seed, registration residual, noise floor.")
    sm.add_argument("--scenario", required=True, metavar="FILE",
                    help="scenario YAML (configs/scenarios/), optional 'data:' block: plan, phases, doe_reps, cell")
    sm.add_argument("--out", required=True, metavar="FILE.csv", help="output CSV")
    sm.add_argument("--seed", type=int, default=None, help="overrides the scenario's and the plan's seed")
    _common(sm)

    def _data_args(q, kinematics=True):
        q.add_argument("--data", required=True, metavar="FILE", help="measurement table CSV (or a foreign file "
                       "with --mapping)")
        q.add_argument("--mapping", default=None, metavar="YAML",
                       help="import mapping for a foreign file (e.g. configs/import/ur10.yaml)")
        q.add_argument("--skip-bad", action="store_true", help="skip bad rows (each is listed) instead of stopping")
        q.add_argument("--seed", type=int, default=0, help="seed of folds and GP restarts (default 0)")
        if not kinematics:
            return
        q.add_argument("--robot", default=None, metavar="YAML",
                       help="robot kinematic model config (default configs/robots/cobot_hc20_like.yaml)")
        q.add_argument("--gp-inputs", default="tcp_speed", choices=("tcp_speed", "tcp", "joints", "none"),
                       help="what the GP on the remaining error sees (default tcp_speed, the paper's)")

    ft = sub.add_parser("fit", help="train an error model (effect terms + GP)",
                        description="error = sum of physical effect terms + GP on what is left. Effects: "
                                    "geometric, compliance, gear, backlash, thermal, dynamic, drift.")
    _data_args(ft)
    ft.add_argument("--effects", default="", metavar="a,b,...", help="effect terms (default none: the paper's GP)")
    ft.add_argument("--out", required=True, metavar="MODEL", help="model directory (JSON + NPZ)")
    ft.add_argument("--cv", type=int, default=0, metavar="K",
                    help="also report the held-out RMS by K-fold CV grouped by target point")
    _common(ft)

    dg = sub.add_parser("diagnose", help="rank the physical effects the model lacks",
                        description="Grouped cross-validation (by target point) of the model with and without "
                                    "each candidate effect; one-sided Wilcoxon test per held-out group.")
    _data_args(dg)
    dg.add_argument("--model", default=None, metavar="MODEL", help="starting model (default: --effects + GP)")
    dg.add_argument("--effects", default="", metavar="a,b,...", help="starting model's effects without --model")
    dg.add_argument("--candidates", default="", metavar="a,b,...", help="effects to test (default all)")
    dg.add_argument("--folds", type=int, default=5, help="cross-validation folds (default 5)")
    _common(dg)

    cp = sub.add_parser("compare", help="error models against measurements, side by side",
                        description="RMS, mean and max 3D error, per axis, Eq. 17 t-test failures and the residual "
                                    "broken down by region, speed, payload, temperature, time and joint "
                                    "configuration, for 'as is' and every --model in the order given.")
    _data_args(cp, kinematics=False)
    cp.add_argument("--model", required=True, action="append", metavar="MODEL",
                    help="model directory from `dt fit`; repeat for a side-by-side comparison (oldest first)")
    cp.add_argument("--names", default="", metavar="a,b,...", help="column names of the models (default: directory names)")
    cp.add_argument("--cv", type=int, default=0, metavar="K",
                    help="held-out figures from the training file: refit each model's configuration on K-1 "
                         "folds grouped by target point (default 0: the models as saved)")
    cp.add_argument("--report", default=None, metavar="DIR", help="write DIR/report.html and DIR/compare.json")
    _common(cp)

    st = sub.add_parser("status", help="current state and last figures from the daemon's store")
    st.add_argument("--store", default="out/run/dt.sqlite", help="the daemon's SQLite store")
    st.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def _common(q: argparse.ArgumentParser) -> None:
    q.add_argument("--json", action="store_true", help="print the result as one JSON object")
    q.add_argument("--no-progress", action="store_true", help="do not show progress on stderr")


class JsonLines(logging.Formatter):
    """One JSON object per log record on stderr: machine-readable logs for the daemon."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": round(record.created, 3), "level": record.levelname, "logger": record.name,
               "msg": record.getMessage()}
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLines() if args.cmd == "run" else
                         logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, handlers=[handler])
    as_json = getattr(args, "json", False)
    try:
        limit_blas_threads()
        result = COMMANDS[args.cmd](args)
    except TwinError as exc:
        if as_json:
            print(json.dumps({"error": str(exc), "type": type(exc).__name__}))
        print(f"dt {args.cmd}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dt {args.cmd}: interrupted", file=sys.stderr)
        return 130
    if as_json:
        print(json.dumps(result))
    else:
        print(_human(args.cmd, result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
