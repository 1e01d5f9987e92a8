"""The layer rules of docs/architecture.md, checked on every import statement (AST walk,
lazy imports inside functions included):

- dt_kernel (errors, config loader, units, geometry) imports nothing else of the project;
- sim imports only dt_kernel; drivers import dt_kernel and sim, never emulators or dt_runtime;
- emulators import dt_kernel, sim and drivers (the protocol codecs); nothing else imports them;
- inside dt_runtime nothing imports upward: each subpackage may import its own and lower
  layers only (LAYERS, lowest first; reports and the command line at the top). The package's
  __init__ is the public facade and may name anything;
- a few layers also keep apart from some lower ones (APART): the fabric, the Zenoh client every
  part of a plant uses, sits below the daemon and imports neither the twin nor its models, so that
  a plant's router, inbox or dashboard loads no GP; the plant and the dashboard use the fabric,
  not the daemon (the dashboard reads a cell's runtime config through its LiveCell protocol).
"""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROJECT = ("dt_kernel", "sim", "drivers", "emulators", "dt_runtime")
# emulators serve the drivers' wire protocols over the simulated plant; nothing of the product
# imports them (a real driver imports no simulator's emulator; tests and benchmarks use them).
ALLOWED = {"dt_kernel": {"dt_kernel"}, "sim": {"dt_kernel", "sim"},
           "drivers": {"dt_kernel", "sim", "drivers"},
           "emulators": {"dt_kernel", "sim", "drivers", "emulators"},
           "dt_runtime": {"dt_kernel", "sim", "drivers", "dt_runtime"}}
LAYERS = ("common", "metrology", "frames", "measurements", "models", "analysis", "twin", "programs", "workflows",
          "fabric", "service", "plant", "reports", "dashboard", "cli")
# Lower layers a layer must not import all the same (the floors are a partial order: the fabric
# sits beside the twin, not on it; the plant talks to its cells through the fabric, never through
# the daemon's modules).
_MODEL_SIDE = ("models", "analysis", "twin", "programs", "workflows")
APART = {"fabric": _MODEL_SIDE, "plant": (*_MODEL_SIDE, "service"), "dashboard": ("service",)}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _load_walker():
    # The one import walker lives with the architecture picture's generator (docs/tools).
    spec = importlib.util.spec_from_file_location("architecture_tool", ROOT / "docs" / "tools" / "architecture.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_walker = _load_walker()


def imported_modules(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in `source`; `from pkg import x` also
    yields pkg.x, which may name a submodule."""
    return [(line, n) for line, name, names in _walker.import_lines(source, module, is_package)
            for n in (name, *(f"{name}.{a}" for a in names))]


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "dt_runtime" or len(parts) < 2:
        return None
    return LAYERS.index(parts[1]) if parts[1] in LAYERS else None


def violations(module: str, source: str, is_package: bool = False) -> list[str]:
    """The rule breaches of one module's imports, as readable lines."""
    top = module.split(".")[0]
    bad = []
    for line, name in imported_modules(source, module, is_package):
        target = name.split(".")[0]
        if target not in PROJECT:
            continue
        where = f"{module}:{line} imports {name}"
        if target not in ALLOWED[top]:
            bad.append(f"{where}: {top} may import only {', '.join(sorted(ALLOWED[top]))}")
            continue
        if top != "dt_runtime" or module == "dt_runtime" or target != "dt_runtime":
            continue
        mine, theirs = _layer(module), _layer(name)
        if theirs is None and name != "dt_runtime.data":
            # `from dt_runtime import X` inside the package would go through the facade (upward)
            if name == "dt_runtime" or name.split(".")[1] not in LAYERS:
                bad.append(f"{where}: import from the subpackage that defines it, not the facade")
            continue
        if mine is not None and theirs is not None and theirs > mine:
            bad.append(f"{where}: {LAYERS[mine]} must not import {LAYERS[theirs]} (a higher layer)")
        elif mine is not None and theirs is not None and LAYERS[theirs] in APART.get(LAYERS[mine], ()):
            bad.append(f"{where}: {LAYERS[mine]} must not import {LAYERS[theirs]} (kept apart)")
    return bad


def project_modules() -> list[Path]:
    return sorted(p for pkg in PROJECT for p in (ROOT / pkg).rglob("*.py"))


def test_every_import_in_the_project_follows_the_layer_rules():
    bad = [v for p in project_modules()
           for v in violations(module_name(p), p.read_text(encoding="utf-8"), p.name == "__init__.py")]
    assert not bad, "layer rule breaches:\n" + "\n".join(bad)


def test_dt_runtime_modules_live_in_a_layer():
    loose = [p.name for p in (ROOT / "dt_runtime").glob("*.py") if p.name != "__init__.py"]
    assert not loose, f"modules outside a layer subpackage: {loose}"
    subs = {p.name for p in (ROOT / "dt_runtime").iterdir() if (p / "__init__.py").exists()}
    assert subs == set(LAYERS), f"subpackages {sorted(subs)} differ from the declared layers {LAYERS}"


# The breaches this layout removed: each must still be caught, or the test above proves nothing.
@pytest.mark.parametrize("module, source", [
    ("drivers.simulated.camera_images", "from dt_runtime.mvs import MarkerTracker"),  # old cycle
    ("drivers.serial.controller", "from dt_runtime.service.store import Store"),
    ("sim.camera_rig", "import drivers.base"),
    ("sim.plant", "from dt_runtime.models import effects"),
    ("dt_kernel.config", "from sim.instruments import Pose"),
    ("dt_runtime.analysis.compare", "from dt_runtime.reports.demo_report import rms_with_U"),  # upward
    ("dt_runtime.analysis.compare", "from dt_runtime.cli.fit import run"),
    ("dt_runtime.models.hybrid", "def f():\n    from dt_runtime.analysis import diagnose\n"),  # lazy
    ("dt_runtime.workflows.demo", "from dt_runtime import HybridModel"),  # through the facade
    ("dt_runtime.models", "from ..analysis import crossval"),  # relative, upward
    ("drivers.ur.driver", "from emulators.ur import UrEmulator"),  # a driver importing its emulator
    ("drivers.registry", "def f():\n    from emulators.serial import ControllerEmulator\n"),
    ("dt_runtime.service.daemon", "from emulators.emulated_cell import EmulatedCell"),
    ("emulators.ur.controller", "from dt_runtime.models import effects"),
    ("dt_runtime.fabric.config", "from dt_runtime.service.store import StoreError"),  # the daemon
    ("dt_runtime.fabric.session", "def f():\n    from dt_runtime.twin.twin import Twin\n"),  # kept apart
    ("dt_runtime.fabric.auth", "from dt_runtime.models.gp import GPRegressor"),
    ("dt_runtime.plant.history", "from dt_runtime.service.store import StoreError"),
    ("dt_runtime.dashboard.app", "from dt_runtime.service.runtime_config import RuntimeConfig"),
    ("dt_runtime.twin.twin", "from dt_runtime.workflows.campaign import Instruments"),  # the twin holds the twin only
    ("dt_runtime.twin.corrector", "from dt_runtime.programs.path import Path"),
    ("dt_runtime.twin.bounds", "from dt_runtime.service.daemon import Daemon"),  # the bounds hold no daemon
    ("dt_runtime.programs.program", "from dt_runtime.workflows.demo import run_demo"),
    ("dt_runtime.fabric.queries", "from dt_runtime.programs.program import read_program"),
])
def test_the_checker_catches_each_kind_of_breach(module, source):
    assert violations(module, source, is_package=module.count(".") == 1)


@pytest.mark.parametrize("module, source", [
    ("drivers.serial.tracker", "from dt_kernel.geometry import spherical_to_cartesian"),
    ("drivers.simulated.devices", "from sim.cell import SimCell"),
    ("dt_runtime.service.daemon", "from dt_runtime.workflows.campaign import Instruments\nfrom drivers import registry"),
    ("dt_runtime.cli.compare", "from dt_runtime.reports.compare_report import write_compare_report"),
    ("dt_runtime.fabric.auth", "from dt_runtime.common import private_files\nfrom dt_kernel.errors import StoreError"),
    ("dt_runtime.service.publisher", "from dt_runtime.fabric.session import encode"),
    ("dt_runtime.workflows.demo", "from dt_runtime.programs.path import Path\nfrom dt_runtime.twin.twin import Twin"),
    ("dt_runtime.programs.path_correct", "from dt_runtime.twin.corrector import Corrector"),
    ("dt_runtime", "from dt_runtime.models.hybrid import HybridModel"),  # the facade
    ("emulators.ur.controller", "from drivers.ur import protocol as rp\nfrom sim.kinematics import TOOL_DOWN"),
    ("emulators.emulated_cell.cell", "from emulators.ur import UrEmulator\nfrom drivers.simulated.devices import SimWorld"),
])
def test_the_checker_allows_downward_imports(module, source):
    assert violations(module, source, is_package=module == "dt_runtime") == []


def test_tests_and_benchmarks_share_only_the_support_package():
    """tests/unit and tests/integration hold tests; what more than one of them (or a benchmark)
    needs lives in tests/support. No test module imports another test module, and the project's
    code and benchmarks import nothing from tests but tests.support (a test may run a benchmark:
    that is the benchmark's own test)."""
    files = sorted([*(ROOT / "tests").rglob("*.py"), *(ROOT / "benchmarks").rglob("*.py"),
                    *(p for pkg in PROJECT for p in (ROOT / pkg).rglob("*.py"))])
    bad = []
    for p in files:
        module = module_name(p)
        for line, name in imported_modules(p.read_text(encoding="utf-8"), module, p.name == "__init__.py"):
            parts = name.split(".")
            if parts[0] == "tests" and len(parts) > 1 and parts[1] not in ("support",) and name != "tests.conftest":
                bad.append(f"{module}:{line} imports {name}: shared helpers belong in tests/support")
            if module.split(".")[0] in PROJECT and parts[0] == "tests":
                bad.append(f"{module}:{line} imports {name}: the product does not import tests")
    assert not bad, "\n".join(bad)
    assert {p.name for p in (ROOT / "tests").glob("test_*.py")} == set(), "tests go in tests/unit or tests/integration"


def test_a_plants_config_loads_neither_the_twin_nor_the_gp():
    """What every cell of a plant needs (its bus config, through the fabric) imports no twin, no
    model and no scikit-learn: a router or a dashboard starts without the GP."""
    code = ("import dt_runtime.plant.config, sys; print(sorted(m for m in sys.modules if m.startswith("
            "('sklearn', 'dt_runtime.twin', 'dt_runtime.models'))))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
