"""A package under tests/support/plugins/ made importable as if installed, without network or pip: its
source on sys.path, and a `*.dist-info` directory (METADATA + entry_points.txt) in a temporary
directory on sys.path, which importlib.metadata finds like an installed package's. Shared by
the effect plugin (tests/unit/test_declared_effects.py) and the driver plugin (tests/integration/test_driver_plugin.py).
"""
from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

PLUGINS = Path(__file__).parent / "plugins"


@contextlib.contextmanager
def installed(tmp_path: Path, package: str, entry_points: Mapping[str, Mapping[str, str]],
              reload: Callable[[], Any], version: str = "0.1.0") -> Iterator[Any]:
    """Install tests/support/plugins/<package> (its import name = the folder's) with `entry_points`
    ({group: {name: "module:attr"}}) for the duration; yields `reload()` (the registry's
    re-read of the entry points) and calls it again once uninstalled."""
    info = tmp_path / f"{package}-{version}.dist-info"
    info.mkdir()
    dist = package.replace("_", "-")
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    (info / "entry_points.txt").write_text("".join(
        f"[{grp}]\n" + "".join(f"{n} = {t}\n" for n, t in eps.items()) for grp, eps in entry_points.items()))
    paths = [str(tmp_path), str(PLUGINS / package)]
    sys.path[:0] = paths
    try:
        yield reload()
    finally:
        for p in paths:
            sys.path.remove(p)
        for mod in [m for m in sys.modules if m == package or m.startswith(package + ".")]:
            sys.modules.pop(mod)
        reload()
