"""The `dt` command line. Every computing command accepts --json and then prints exactly one
JSON object on stdout; logs and progress go to stderr. Errors exit with status 2 and, with
--json, print {"error": ...} so scripts always get one object."""
from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Callable

from dt_runtime.errors import TwinError
from dt_runtime.progress import Progress

log = logging.getLogger("dt")
COMMANDS: dict[str, Callable[[argparse.Namespace], dict]] = {}


def command(name: str):
    def deco(fn):
        COMMANDS[name] = fn
        return fn
    return deco


@command("demo")
def _demo(args: argparse.Namespace) -> dict:
    from dt_runtime.demo import run_demo

    res = run_demo(args.out, quick=args.quick, seed=args.seed, config=args.config,
                   progress=Progress(enabled=not args.no_progress), camera=args.camera)
    return res.summary


@command("run")
def _run(args: argparse.Namespace) -> dict:
    from dt_runtime.runtime import run_daemon

    return run_daemon(args.config, args.duration)


@command("status")
def _status(args: argparse.Namespace) -> dict:
    from pathlib import Path

    from dt_runtime.store import Store

    if not Path(args.store).exists():
        raise TwinError(f"{args.store}: no such store (start `dt run` first)")
    with Store(args.store) as st:
        return st.last_figures()


def _human(name: str, result: dict) -> str:
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

    st = sub.add_parser("status", help="current state and last figures from the daemon's store")
    st.add_argument("--store", default="out/run/dt.sqlite", help="the daemon's SQLite store")
    st.add_argument("--json", action="store_true", help="print one JSON object")
    return p


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
