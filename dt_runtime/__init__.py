"""The digital twin as a library: read and import measurements, fit error models (GP, physical
effects + GP), diagnose the missing effect, compare models, state uncertainty budgets, and
load a calibrated twin.

    >>> from dt_runtime import HybridModel, read_table, diagnose, compare   # doctest: +SKIP

Names are imported on first use (PEP 562), so `import dt_runtime` stays cheap and a name's
subpackage loads only when asked for: fitting a model never imports the daemon, the drivers
or matplotlib. The subpackages, lowest layer first, are listed in docs/architecture.md.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from dt_kernel.errors import (
    ConfigError,
    DataError,
    DriverError,
    ModelError,
    StateError,
    TwinError,
    UnreachableError,
)

# public name -> the module that defines it
_EXPORTS: dict[str, str] = {
    # measurements
    "Dataset": "dt_runtime.measurements.dataset",
    "read_table": "dt_runtime.measurements.dataset",
    "write_table": "dt_runtime.measurements.dataset",
    "import_file": "dt_runtime.measurements.importer",
    "load_mapping": "dt_runtime.measurements.importer",
    # frames
    "RigidTransform": "dt_runtime.frames.registration",
    "fit_rigid": "dt_runtime.frames.registration",
    "load_robot": "dt_runtime.frames.kinematics",
    # models
    "MultiOutputGP": "dt_runtime.models.gp",
    "GPOptions": "dt_runtime.models.gp",
    "HybridModel": "dt_runtime.models.hybrid",
    "Effect": "dt_runtime.models.effects",
    "effect_names": "dt_runtime.models.effects",
    # metrology
    "Budget": "dt_runtime.metrology.uncertainty",
    "Component": "dt_runtime.metrology.uncertainty",
    "t_test": "dt_runtime.metrology.uncertainty",
    # analysis
    "load_data": "dt_runtime.analysis.data",
    "cross_validate": "dt_runtime.analysis.crossval",
    "diagnose": "dt_runtime.analysis.diagnose",
    "DiagnoseOptions": "dt_runtime.analysis.options",
    "compare": "dt_runtime.analysis.compare",
    "FitResult": "dt_runtime.analysis.results",
    "DiagnoseResult": "dt_runtime.analysis.results",
    "CompareResult": "dt_runtime.analysis.results",
    # the twin
    "Twin": "dt_runtime.twin.twin",
}

_RENAMED = {"effect_names": "names"}  # a module-level name too generic for the package's namespace

__all__ = [
    "__version__",
    "Budget",
    "compare",
    "CompareResult",
    "Component",
    "ConfigError",
    "cross_validate",
    "DataError",
    "Dataset",
    "diagnose",
    "DiagnoseOptions",
    "DiagnoseResult",
    "DriverError",
    "Effect",
    "effect_names",
    "fit_rigid",
    "FitResult",
    "GPOptions",
    "HybridModel",
    "import_file",
    "load_data",
    "load_mapping",
    "load_robot",
    "ModelError",
    "MultiOutputGP",
    "read_table",
    "RigidTransform",
    "StateError",
    "t_test",
    "Twin",
    "TwinError",
    "UnreachableError",
    "write_table",
]


def __getattr__(name: str) -> Any:
    if name == "__version__":
        from dt_runtime.common.version import version

        return version()
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dt_runtime' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), _RENAMED.get(name, name))
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what type checkers and IDEs see for the lazy names
    from dt_runtime.analysis.compare import compare
    from dt_runtime.analysis.crossval import cross_validate
    from dt_runtime.analysis.data import load_data
    from dt_runtime.analysis.diagnose import diagnose
    from dt_runtime.analysis.results import CompareResult, DiagnoseResult, FitResult
    from dt_runtime.frames.kinematics import load_robot
    from dt_runtime.frames.registration import RigidTransform, fit_rigid
    from dt_runtime.measurements.dataset import Dataset, read_table, write_table
    from dt_runtime.measurements.importer import import_file, load_mapping
    from dt_runtime.metrology.uncertainty import Budget, Component, t_test
    from dt_runtime.models.effects import Effect
    from dt_runtime.models.effects import names as effect_names
    from dt_runtime.models.gp import GPOptions, MultiOutputGP
    from dt_runtime.models.hybrid import HybridModel
    from dt_runtime.twin.twin import Twin
