"""Lower-level errors are converted once per boundary (docs/architecture.md: the layer rules): sqlite3 in the
store, pyserial/OS errors in the serial link, zenoh in the bus session module; each raises the
project's error `from` the original."""
from __future__ import annotations

import ast
import sqlite3
from pathlib import Path

import pytest
import zenoh

from dt_kernel.errors import DriverError, TwinError
from dt_runtime.fabric import BusConfig, BusError
from dt_runtime.fabric.session import zenoh_errors
from dt_runtime.service.store import Store, StoreError

ROOT = Path(__file__).resolve().parents[2]
# boundary -> (names whose exceptions it converts, the one module allowed to catch them)
BOUNDARIES = {"sqlite": (("sqlite3",), "dt_runtime/service/store.py"),
              "serial": (("serial", "SerialException"), "drivers/serial/link.py"),
              "zenoh": (("zenoh", "ZError"), "dt_runtime/fabric/session.py")}


def handlers_naming(names: tuple[str, ...]) -> list[str]:
    """'path:line' of every `except` clause in the project that names one of `names`."""
    out = []
    for pkg in ("dt_kernel", "sim", "drivers", "dt_runtime"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ExceptHandler) and node.type is not None:
                    used = {n.id for n in ast.walk(node.type) if isinstance(n, ast.Name)}
                    if used & set(names):
                        out.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    return out


@pytest.mark.parametrize("boundary", ["sqlite", "serial"])
def test_each_boundary_catches_its_library_errors_in_one_place(boundary):
    names, module = BOUNDARIES[boundary]
    found = handlers_naming(names)
    assert len(found) == 1 and found[0].startswith(module + ":"), found


def test_zenoh_errors_are_converted_in_the_session_module_only():
    assert handlers_naming(BOUNDARIES["zenoh"][0]) == []  # zenoh's types are never caught elsewhere
    src = (ROOT / BOUNDARIES["zenoh"][1]).read_text()
    assert "raise BusError(" in src and "from exc" in src
    with pytest.raises(BusError) as ei:
        BusConfig(extra={"no/such/key": 1}).zenoh_config()
    assert isinstance(ei.value, DriverError) and isinstance(ei.value.__cause__, zenoh.ZError)
    with pytest.raises(StoreError):  # the project's own errors pass through unchanged
        with zenoh_errors("x"):
            raise StoreError("kept")


def test_store_errors_chain_the_sqlite_error(tmp_path):
    (tmp_path / "dir.db").mkdir()
    with pytest.raises(StoreError) as ei:
        Store(tmp_path / "dir.db")
    assert isinstance(ei.value, TwinError) and isinstance(ei.value.__cause__, sqlite3.Error)
