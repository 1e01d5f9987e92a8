"""A re-mounted session of the demo's simulated cell: new uncorrected poses inside the twin's
calibrated volume measured through the demo's simulated drivers (`measure`), as the instruments
see them after the robot's base was re-mounted (every measured point moved by one small rigid
motion of GL), split into N reference poses spread over the volume (the daily check's file) and
the other poses (to score the twin on): `remount`."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dt_runtime.analysis.deployment import reference_rows
from dt_runtime.frames.registration import RigidTransform
from dt_runtime.measurements.campaign_files import read_phase, write_phase
from dt_runtime.twin.twin import Twin


def measure(twin: Twin, doe_points: np.ndarray, n: int, seed: int):
    """n new uncorrected poses inside the twin's calibrated volume, measured on the demo's cell (PhaseData)."""
    from dt_kernel.config import load_yaml
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.measurements.plans import PlanRow
    from dt_runtime.workflows.campaign import run_rows
    from dt_runtime.workflows.coverage_check import sample_targets
    from dt_runtime.workflows.demo import DemoConfig, _open

    cfg = load_yaml(CONFIGS / "demo.yaml", DemoConfig)
    inst, world = _open(cfg, CONFIGS, seed)
    try:
        rng = np.random.default_rng(seed)
        assert twin.volume is not None
        targets = sample_targets(twin.volume, doe_points, n, (-np.inf, 0.0), world, rng)
        rows = [PlanRow("validation", i + 1, 0, t, 0.5) for i, t in enumerate(targets)]
        return run_rows(inst, rows, label="session", skip_unreachable=True)
    finally:
        inst.close()


def remount(twin_dir: Path, doe: Path, out: Path, shift_mm=(1.5, -1.0, 0.8), rot_mrad=(0.3, -0.2, 0.5),
            k: int = 10, n: int = 40, seed: int = 5) -> tuple[Path, Path]:
    """Write out/reference.csv (k spread poses) and out/session.csv (the rest) of the moved session."""
    twin = Twin.load(twin_dir)
    ph = measure(twin, np.unique(read_phase(doe, "doe").p_rdk, axis=0), n + k, seed)
    M = RigidTransform(Rotation.from_rotvec(np.asarray(rot_mrad) * 1e-3).as_matrix(), np.asarray(shift_mm) * 1e-3)

    def moved(T: RigidTransform, p: np.ndarray | None) -> np.ndarray | None:
        if p is None:
            return None
        return T.inverse().apply(M.apply(T.apply(p)))  # the instrument sees the point where GL moved it

    ph = replace(ph, p_lt=moved(twin.T_lt, ph.p_lt), p_mvs=moved(twin.T_mvs, ph.p_mvs),
                 truth_lt=moved(twin.T_lt, ph.truth_lt))
    ref = reference_rows(ph.p_rdk, k)
    out.mkdir(parents=True, exist_ok=True)
    return write_phase(out / "reference.csv", ph.rows(ref)), write_phase(out / "session.csv", ph.rows(~ref))
