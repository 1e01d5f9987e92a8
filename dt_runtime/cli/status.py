"""`dt status`: the daemon's current state and last figures, read from its store."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from dt_kernel.errors import TwinError


def add_arguments(st: argparse.ArgumentParser) -> None:
    st.add_argument("--store", default="out/run/dt.sqlite", help="the daemon's SQLite store")
    st.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> Any:
    from dt_runtime.service.store import Store

    if not Path(args.store).exists():
        raise TwinError(f"{args.store}: no such store (start `dt run` first)")
    with Store(args.store) as st:
        return st.last_figures()


def human(result: dict) -> str:
    return json.dumps(result, indent=2)
