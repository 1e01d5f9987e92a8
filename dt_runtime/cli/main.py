"""The `dt` command line. Every computing command accepts --json and then prints exactly one
JSON object on stdout; logs and progress go to stderr. Errors exit with status 2 and, with
--json, print {"error": ..., "type": ...} so scripts always get one object; an internal error
(a defect) exits 1, logs its traceback on stderr and, with --json, prints the same object.

Each command is one module of this package (arguments, run, human text); this module only
assembles them."""
from __future__ import annotations

import argparse
import json
import logging
import sys
from types import ModuleType

from dt_kernel.errors import TwinError
from dt_runtime.cli import (
    ack,
    calibrate,
    campaign,
    compare,
    consume,
    correct,
    dashboard,
    demo,
    diagnose,
    export,
    fit,
    robots,
    router,
    run,
    simulate,
    status,
)
from dt_runtime.common.jsonsafe import dumps, jsonable
from dt_runtime.common.logs import RepeatFilter
from dt_runtime.common.threads import limit_blas_threads_when_loaded
from dt_runtime.common.version import version_string

COMMANDS: dict[str, tuple[ModuleType, str]] = {  # name -> (module, one-line help); the module's docstring describes it
    "demo": (demo, "the paper's whole experiment on the simulated cell"),
    "calibrate": (calibrate, "a twin from a campaign's measurement files"),
    "campaign": (campaign, "run the calibration campaign through a runtime YAML's drivers, then calibrate"),
    "run": (run, "the long-running twin daemon"),
    "simulate": (simulate, "measurement data from the simulated cell"),
    "fit": (fit, "train an error model (effect terms + GP)"),
    "diagnose": (diagnose, "rank the physical effects the model lacks"),
    "compare": (compare, "error models against measurements, side by side"),
    "export": (export, "export the calibrated robot as URDF or DH robot config"),
    "correct": (correct, "corrected commands for a program, with their uncertainty"),
    "robots": (robots, "the catalogue of robot arms --robot can name"),
    "status": (status, "current state and last figures from the daemon's store"),
    "ack": (ack, "confirm that maintenance was done (or a request delivered)"),
    "consume": (consume, "receive and acknowledge maintenance requests (a maintenance system's side)"),
    "dashboard": (dashboard, "the live cell in a browser, beside a running `dt run`"),
    "router": (router, "run the plant's Zenoh router (cells and the plant's tools connect to it)"),
}


class _Version(argparse.Action):
    """``--version``: the version and the git commit, asked of git only when given (two git
    processes on every ``dt`` command, even an argument error, were most of its start-up)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kw) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kw)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"dt {version_string()}")  # on stdout, as argparse's own version action
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    """The ``dt`` parser: global options and one subparser per command (its module's docstring as the description).

    Returns
    -------
    argparse.ArgumentParser
    """
    p = argparse.ArgumentParser(prog="dt", description="Traceable digital twin of a collaborative robot arm.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging on stderr")
    p.add_argument("--version", action=_Version, help="print the version and the git commit, then exit")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for name, (mod, help_) in COMMANDS.items():
        mod.add_arguments(sub.add_parser(name, help=help_, description=mod.__doc__,
                                         formatter_class=argparse.RawDescriptionHelpFormatter))
    return p


def parse(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse ``argv``; an option the command does not know is refused by the command's own parser
    (``dt demo: error: unrecognized arguments: --quik``, its usage, exit 2), not by the top-level one,
    whose usage lists only the commands.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        What ``build_parser`` made.
    argv : list of str or None
        The arguments (sys.argv[1:] when None).

    Returns
    -------
    argparse.Namespace
    """
    args, extra = parser.parse_known_args(argv)
    if extra:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        sub.choices[args.cmd].error(f"unrecognized arguments: {' '.join(extra)}")
    return args


class JsonLines(logging.Formatter):
    """One JSON object per log record on stderr: machine-readable logs for the daemon (a record's
    `fields`, e.g. of its status line, go in beside the message)."""

    def format(self, record: logging.LogRecord) -> str:
        """One log record as a JSON object: ts, level, logger, msg, the record's ``fields``, and the
        traceback when there is one.

        Parameters
        ----------
        record : logging.LogRecord

        Returns
        -------
        str
        """
        out = {"ts": round(record.created, 3), "level": record.levelname, "logger": record.name,
               "msg": record.getMessage()} | (getattr(record, "fields", None) or {})
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def main(argv: list[str] | None = None) -> int:
    """The ``dt`` entry point: parse, run the command, print its result (JSON or text).

    Parameters
    ----------
    argv : list of str or None
        The arguments (sys.argv[1:] when None).

    Returns
    -------
    int
        Exit status: 0, the command's own (``exit_code``, e.g. 3 with --strict), 2 for a TwinError
        (bad input), 130 on Ctrl-C, 1 for an internal error.
    """
    args = parse(build_parser(), argv)
    mod = COMMANDS[args.cmd][0]
    handler = logging.StreamHandler(sys.stderr)
    json_logs = getattr(mod, "json_logs", None)  # the command decides (dt run: by --log-format), or says JSON_LOGS
    as_lines = json_logs(args) if json_logs is not None else getattr(mod, "JSON_LOGS", False)
    handler.setFormatter(JsonLines() if as_lines else
                         logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.addFilter(RepeatFilter())  # a failing disk logged one error 87 times a second
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, handlers=[handler])
    as_json = getattr(args, "json", False)
    try:
        limit_blas_threads_when_loaded()
        result = jsonable(mod.run(args))
    except TwinError as exc:
        if as_json:
            print(json.dumps({"error": str(exc), "type": type(exc).__name__}))
        print(f"dt {args.cmd}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dt {args.cmd}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a defect, not bad input: the traceback for us, one JSON object for scripts
        logging.getLogger("dt").exception("dt %s: internal error", args.cmd)
        if as_json:
            print(json.dumps({"error": f"internal error: {exc}", "type": type(exc).__name__}))
        return 1
    print(dumps(result) if as_json else mod.human(result))
    # a command may end with another status on a result it did write (dt demo/calibrate --strict)
    return mod.exit_code(args, result) if hasattr(mod, "exit_code") else 0


if __name__ == "__main__":
    sys.exit(main())
