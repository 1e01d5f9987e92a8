"""What must hold before the daemon opens anything: a failed check raises ConfigError naming the
file and key, and `dt run` exits non-zero with nothing to close.

The twin must have been calibrated with the daemon's camera driver, every condition its maps
read must have a source, and its maps must predict finite errors.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from drivers import registry
from dt_kernel.errors import ConfigError, TwinError
from dt_runtime.service.runtime_config import Drivers
from dt_runtime.twin.twin import Twin


def check_camera(twin: Twin, twin_dir: Path, camera_kind: str) -> None:
    """A twin is valid only with the camera driver it was calibrated with.

    Parameters
    ----------
    twin : Twin
        The loaded twin.
    twin_dir : Path
        Its directory (named in the error).
    camera_kind : str
        The daemon's `drivers.camera.kind`.
    """
    trained = twin.instruments.get("camera")
    if trained and trained != camera_kind:
        raise ConfigError(str(twin_dir / "twin.json"), "instruments.camera", trained,
                          f"the daemon's camera driver '{camera_kind}': a twin is valid only "
                          "with the instruments (and frames) it was calibrated with")


def check_condition_sources(twin: Twin, twin_dir: Path, drivers: Drivers, program: Any) -> None:
    """Every condition the twin's maps read must have a source, or the start fails (not every
    command later): joint angles from the controller, the clock always; temperature and payload
    from the program's columns or the simulated cell (a real cell's sensor driver: not yet
    available).

    Parameters
    ----------
    twin : Twin
        The loaded twin.
    twin_dir : Path
        Its directory (named in the error).
    drivers : Drivers
        The runtime config's drivers.
    program : Program or None
        The point program, when `path.kind` is `program`.
    """
    sim = any(registry.needs_world(k, n) for k, n, _ in drivers.chosen())
    for need in twin.needs:
        if need in ("temperature", "payload") and not sim and getattr(program, need, None) is None:
            raise ConfigError(str(twin_dir / "twin.json"), "e_lt effects", need,
                              f"a source of {need}: a program (path.kind program) with a {need} column, or "
                              "the simulated cell's drivers")


def check_model(twin: Twin, twin_dir: Path, probe: np.ndarray, speed: float) -> None:
    """The twin's maps must predict finite errors: a model file with NaN in it stops the start
    (exit non-zero, nothing opened) instead of refusing every command later. Probed at the
    path's first target; a map that also reads conditions is not probed here (it is checked
    command by command: a NaN there is refused, counted and, repeated, halts).

    Parameters
    ----------
    twin : Twin
        The loaded twin.
    twin_dir : Path
        Its directory (named in the error).
    probe : ndarray
        (3,) m: where the predictions are probed.
    speed : float
        m/s, the speed they are probed at.
    """
    if twin.needs:
        return
    try:
        e = np.concatenate([np.ravel(twin.e_lt_hat(probe, speed)[0]), np.ravel(twin.e_mvs_lt_hat(probe, speed)[0])])
    except (TwinError, ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        raise ConfigError(str(twin_dir), "e_lt", "unusable", f"a model that predicts ({exc})") from exc
    if not np.all(np.isfinite(e)):
        raise ConfigError(str(twin_dir), "e_lt", f"prediction {e.tolist()} m",
                          "finite predictions: the model file holds NaN or inf (refit it)")
