"""A multi-session laser-tracker campaign written the way the instruments export it (issue 13,
part 7): per session a tracker file of points only (Latin-1, a German header with '°', measured
positions in the tracker's own frame, the tracker set up anew each session) and the controller's
joint angles in a separate spreadsheet CSV (';', decimal comma, degrees, UTF-8 with a byte-order
mark), joined by the point number. No commanded positions anywhere: the twin computes them from
the joints with the robot config.

The truth is the independent UR10 generator's forward kinematics (tests/support/ur10_generator.py) with
its geometric errors (DH lengths +-0.2 mm, angles and joint zeros +-0.2 mrad, 1 sigma); the
nominal model the twin is given is configs/robots/ur10.yaml.

    truth = write_campaign(tmp_path, seed=7)   # s1.csv, s1_joints.csv, ..., mapping.yaml

`layout="days"` writes the same campaign the way a hall's instruments lay it out in folders
(issue 21, part 6): day1/points.csv, day1/joints.xlsx, day2/points.csv, ... (the same file names
in every folder); the tracker file also states each point's expanded uncertainty U95 (k = 2) per
axis and carries the hall's weather station (air pressure, humidity), and the joints are the
controller's spreadsheet as it saved it (a cover sheet, then the sheet 'Achsen', numbers as
numbers), read by MAPPING_DAYS.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from tests.support.spreadsheet_files import write_xlsx
from tests.support.ur10_generator import ALPHA, A, D, fk

JOINT_COLS = [f"Achse {j} [°]" for j in range(1, 7)]
TRACKER_COLS = ["Punkt", "X [mm]", "Y [mm]", "Z [mm]", "Temperatur [°C]"]
# the training sessions' joint ranges (rad; elbow up, wrist 3 within +-170 deg)
LO = np.array([-1.3, -2.3, -2.3, -2.6, 0.6, np.deg2rad(-170)])
HI = np.array([1.3, -0.9, -0.7, -0.6, 2.5, np.deg2rad(170)])
WRIST_MAX_DEG = 259.0  # the test session turns wrist 3 beyond anything trained

MAPPING = """\
format_version: 1
description: "tracker points (Latin-1, ',') joined by 'Punkt' to the controller's joints (';', decimal comma, deg)"
separator: ","
encoding: latin-1
columns: {mx: "X [mm]", my: "Y [mm]", mz: "Z [mm]", point_id: Punkt, temperature: "Temperatur [°C]"}
units: {measurement: mm}
measured_frame: instrument
registration: {fit_offset: false}
time: row_order
joints:
  path: "{stem}_joints.csv"
  separator: ";"
  decimal: ","
  encoding: utf-8-sig
  columns: ["Achse 1 [°]", "Achse 2 [°]", "Achse 3 [°]", "Achse 4 [°]", "Achse 5 [°]", "Achse 6 [°]"]
  unit: deg
  join: {key: Punkt}
robot: configs/robots/ur10.yaml   # beside the mapping, else the working directory, else the project
"""


MAPPING_DAYS = """\
format_version: 1
description: "tracker points (Latin-1, ',', U95 with k = 2) joined by 'Punkt' to the controller's joints (.xlsx, deg)"
separator: ","
encoding: latin-1
columns: {mx: "X [mm]", my: "Y [mm]", mz: "Z [mm]", point_id: Punkt, temperature: "Temperatur [°C]",
          ux: "U95 X [mm]", uy: "U95 Y [mm]", uz: "U95 Z [mm]"}
units: {measurement: mm, uncertainty: mm}
uncertainty: {kind: expanded, k: 2}   # the tracker states U95 = 2 u per axis
measured_frame: instrument
registration: {fit_offset: false}
time: row_order
joints:
  path: joints.xlsx              # beside each points.csv: day1/joints.xlsx, day2/joints.xlsx, ...
  sheet: Achsen                  # the second sheet; the first is the controller's cover sheet
  columns: ["Achse 1 [°]", "Achse 2 [°]", "Achse 3 [°]", "Achse 4 [°]", "Achse 5 [°]", "Achse 6 [°]"]
  unit: deg
  join: {key: Punkt}
robot: configs/robots/ur10.yaml
"""
WEATHER_COLS = ["U95 X [mm]", "U95 Y [mm]", "U95 Z [mm]", "Luftdruck [hPa]", "Luftfeuchte [%]"]


def arm(seed: int) -> dict:
    """The true arm's geometric errors, as ur10_generator draws them."""
    rng = np.random.default_rng(1000 + seed)
    return {"a": A + rng.normal(0, 2e-4, 6) * (A != 0), "d": D + rng.normal(0, 2e-4, 6),
            "alpha": ALPHA + rng.normal(0, 2e-4, 6), "theta0": rng.normal(0, 2e-4, 6)}


def tracker_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A tracker set up somewhere 2-3 m from the base, turned anyhow about its vertical and
    slightly tilted: instrument -> robot, p_robot = R p_inst + t (m)."""
    R = Rotation.from_euler("zyx", [rng.uniform(-np.pi, np.pi), rng.normal(0, 0.01), rng.normal(0, 0.01)]).as_matrix()
    ang = rng.uniform(-np.pi, np.pi)
    t = np.array([2.5 * np.cos(ang), 2.5 * np.sin(ang), rng.uniform(-0.5, 0.2)])
    return R, t


def _num(v: float, decimals: int, comma: bool) -> str:
    s = f"{v:.{decimals}f}"
    return s.replace(".", ",") if comma else s


def write_session(folder: Path, name: str, q_deg: np.ndarray, passes: int, pose, geo: dict,
                  rng: np.random.Generator, noise_mm: float, weather: np.random.Generator | None = None) -> dict:
    """One session: `name`.csv (tracker) and `name`_joints.csv (controller); with `weather` (the
    hall's weather station, its own random stream), `name`/points.csv (with U95 and the weather)
    and `name`/joints.xlsx. Returns its truth."""
    q = np.deg2rad(q_deg)
    n_points = len(q)
    order = np.concatenate([rng.permutation(n_points) for _ in range(passes)])
    actual = fk(q[order], **geo)  # where the true arm put the probe, robot frame
    measured = actual + rng.normal(0, noise_mm * 1e-3, actual.shape)
    R, t = pose
    inst = (measured - t) @ R  # R^T (p - t) row by row: the tracker's own coordinates
    air = 20.5 + 0.3 * np.sin(np.linspace(0, np.pi, len(order)))  # the tracker's weather station (deg C)
    rows = [",".join([str(i + 1)] + [_num(v * 1e3, 4, False) for v in p] + [_num(a, 2, False)])
            for i, p, a in zip(order, inst, air)]
    days = weather is not None
    if days:
        folder = folder / name
        folder.mkdir(parents=True, exist_ok=True)
        pressure = 1013.2 + np.cumsum(weather.normal(0, 0.05, len(order)))
        humidity = 45.0 + np.cumsum(weather.normal(0, 0.2, len(order)))
        u95 = _num(2 * noise_mm, 4, False)  # the tracker's stated U95 per axis: k = 2 times its noise
        rows = [f"{r},{u95},{u95},{u95},{_num(pa, 2, False)},{_num(h, 1, False)}"
                for r, pa, h in zip(rows, pressure, humidity)]
        (folder / "points.csv").write_text(",".join(TRACKER_COLS + WEATHER_COLS) + "\n" + "\n".join(rows) + "\n",
                                           encoding="latin-1")
        write_xlsx(folder / "joints.xlsx", {
            "Deckblatt": [["Roboter", "UR10"], ["Programm", f"Messfahrt {name}"]],
            "Achsen": [["Punkt", *JOINT_COLS]] + [[i + 1, *(float(v) for v in q_deg[i])] for i in range(n_points)]})
    else:
        (folder / f"{name}.csv").write_text(",".join(TRACKER_COLS) + "\n" + "\n".join(rows) + "\n",
                                            encoding="latin-1")
        jrows = [";".join([str(i + 1)] + [_num(v, 4, True) for v in q_deg[i]]) for i in range(n_points)]
        (folder / f"{name}_joints.csv").write_text(";".join(["Punkt"] + JOINT_COLS) + "\n" + "\n".join(jrows)
                                                   + "\n", encoding="utf-8-sig")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t * 1e3  # the set-up as a surveyor would hand it over (mm)
    np.savetxt(folder / ("trafo.txt" if days else f"{name}_trafo.txt"), T, fmt="%.10f")
    return {"q": q[order], "commanded": fk(q[order]), "actual": actual, "R": R, "t": t, "order": order}


def write_campaign(folder: Path, seed: int = 7, n_points: int = 30, passes: int = 2, noise_mm: float = 0.01,
                   sessions: int = 3, layout: str = "flat") -> dict:
    """`sessions` sessions s1..sN of one arm (the last one with wrist 3 up to 259 deg) and the
    mapping that reads them all (mapping.yaml); `layout="days"`: day1/points.csv, day1/joints.xlsx,
    ... and MAPPING_DAYS (the same arm and poses for the same seed). Returns {'files', 'mapping',
    'geo', 'sessions'}."""
    if layout not in ("flat", "days"):
        raise ValueError(f"layout {layout!r}: 'flat' or 'days'")
    days = layout == "days"
    weather = np.random.default_rng(500 + seed)  # its own stream: the arm and poses stay those of 'flat'
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    geo = arm(seed)
    truth = []
    for s in range(sessions):
        q_deg = np.rad2deg(LO + (HI - LO) * rng.random((n_points, 6)))
        if s == sessions - 1:  # the new task: wrist 3 from 100 to 259 deg
            q_deg[:, 5] = np.linspace(100.0, WRIST_MAX_DEG, n_points)[rng.permutation(n_points)]
        q_deg = np.round(q_deg, 4)  # what the file holds is the truth the arm was commanded with
        name = f"day{s + 1}" if days else f"s{s + 1}"
        truth.append(write_session(folder, name, q_deg, passes, tracker_pose(rng), geo, rng, noise_mm,
                                   weather if days else None))
    (folder / "mapping.yaml").write_text(MAPPING_DAYS if days else MAPPING, encoding="utf-8")
    files = [folder / f"day{s + 1}" / "points.csv" if days else folder / f"s{s + 1}.csv" for s in range(sessions)]
    return {"files": files, "mapping": folder / "mapping.yaml", "geo": geo, "sessions": truth}
