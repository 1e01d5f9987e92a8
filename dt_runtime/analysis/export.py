"""Export the calibrated robot: the identifiable combinations of a fitted model's `geometric`
effect applied to the nominal kinematic chain, written as a URDF or a standard DH table in the
robot config format, loaded back and checked (`export_robot`). See docs/cli.md ("dt export").
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dt_kernel.errors import ConfigError, DataError, ModelError, TwinError
from dt_kernel.units import MM_PER_M
from dt_runtime.analysis.data import Data, load_data
from dt_runtime.common.jsonsafe import jsonable
from dt_runtime.common.paths import ROOT
from dt_runtime.common.provenance import FileRecord, Provenance, build, files_under, sha256_file
from dt_runtime.common.safe_json import read_json
from dt_runtime.frames import robots
from dt_runtime.frames.kinematics import Chain, chain_from_urdf, load_robot
from dt_runtime.frames.robot_export import dh_table, urdf_text
from dt_runtime.models.effects import Inputs
from dt_runtime.models.effects.geometric import Geometric
from dt_runtime.models.hybrid import HybridModel, resolve_chain
from dt_runtime.models.identifiability import ALIAS_RTOL, Aliasing, aliasing

FORMATS = ("urdf", "dh")
FK_TOL_MM = 0.01
NO_GEOMETRIC = "fit one with dt fit --effects geometric ..."


# --------------------------------------------------------------------------- the calibrated chain
def _rotvec_T(w: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(w).as_matrix()
    return T


def _trans_T(d: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = d
    return T


def calibrated_chain(chain: Chain, values: dict[str, float]) -> Chain:
    """The chain with the geometric parameters (name -> value, SI) applied exactly: joint j's
    origin becomes origin_j Trans(d_j) Rot(w_j) Rot(axis_j, offset_j), the tool tool Trans(d_tool).

    Parameters
    ----------
    chain : Chain
        The nominal chain.
    values : dict of str to float
        Geometric parameters, SI.

    Returns
    -------
    Chain
    """
    dof = chain.dof
    d = np.zeros((dof, 3))
    w = np.zeros((dof, 3))
    off = np.zeros(dof)
    tool = np.zeros(3)
    for name, v in values.items():
        if name.startswith("offset_q"):
            off[int(name[8:]) - 1] = v
        elif name.startswith("frame"):
            j, kind = name[5:].split("_")
            (d if kind[0] == "d" else w)[int(j) - 1, "xyz".index(kind[1])] = v
        elif name.startswith("tool_d"):
            tool["xyz".index(name[6])] = v
        else:
            raise ModelError(f"unknown geometric parameter {name!r}")
    origins = tuple(chain.origins[j] @ _trans_T(d[j]) @ _rotvec_T(w[j])
                    @ _rotvec_T(off[j] * np.asarray(chain.axes[j], dtype=float)) for j in range(dof))
    return replace(chain, origins=origins, tool=chain.tool @ _trans_T(tool))


def _values(names: tuple[str, ...], theta: np.ndarray) -> dict[str, float]:
    return {nm: float(v) for nm, v in zip(names, theta) if v != 0.0}


def refine(chain: Chain, names: tuple[str, ...], theta: np.ndarray, basis: tuple[int, ...], q: np.ndarray,
           target: np.ndarray, iterations: int = 8, tol_m: float = 1e-10) -> np.ndarray:
    """The basis parameters adjusted (Gauss-Newton, from `theta`) so that the chain with them
    applied exactly reaches `target` (n, 3) at q: what the first-order model predicts, without
    its second-order error at large parameters. Non-basis parameters stay zero.

    Parameters
    ----------
    chain : Chain
        The nominal chain.
    names : tuple of str
        The geometric parameters' names.
    theta : ndarray
        (p,) start.
    basis : tuple of int
        The parameters adjusted.
    q : ndarray
        (n, dof) joint angles, rad.
    target : ndarray
        (n, 3), m.
    iterations : int, optional
        At most this many steps.
    tol_m : float, optional
        Stop when the step's RMS change is below this, m.

    Returns
    -------
    ndarray
        (p,).
    """
    theta = theta.copy()
    cols = list(basis)
    if not cols:
        return theta
    for _ in range(iterations):
        cur = calibrated_chain(chain, _values(names, theta))
        r = (target - cur.fk(q)).reshape(-1)
        A = Geometric().build(Inputs(cur.fk(q), joints=q), cur).A[:, :, cols].reshape(len(r), -1)
        # measured moves by -A dtheta (e = -A ... sign: e = commanded - measured = A theta)
        step = np.linalg.lstsq(-A, r, rcond=None)[0]
        theta[cols] += step
        if np.max(np.abs(A @ step)) < tol_m:
            break
    return theta


# --------------------------------------------------------------------------- the result
@dataclass
class ExportResult:
    """What `dt export` wrote and how well it holds the calibration."""

    out: str
    format: str
    model: str
    robot: str | None
    data: str
    n_points: int
    n_parameters: int
    rank: int
    exported: list[dict]  # basis parameters: name, unit, value (exported), fitted, absorbs
    not_identifiable: list[dict]  # name, unit, fitted, absorbed_by {name: coefficient}
    no_effect: list[str]  # columns zero over the data: no effect on the TCP there
    alias_groups: list[list[str]]
    singular_values: list[float]
    fk_check: dict
    loads_back: dict
    warnings: list[str] = field(default_factory=list)
    provenance: Provenance | None = None

    def to_dict(self) -> dict[str, Any]:
        """The result as the JSON object of `dt export --json` (docs/cli.md)."""
        return jsonable({"out": self.out, "format": self.format, "model": self.model, "robot": self.robot,
                         "data": self.data, "n_points": self.n_points, "n_parameters": self.n_parameters,
                         "rank": self.rank, "n_exported": len(self.exported),
                         "n_not_identifiable": len(self.not_identifiable) + len(self.no_effect),
                         "exported": self.exported, "not_identifiable": self.not_identifiable,
                         "no_effect": self.no_effect, "alias_groups": self.alias_groups,
                         "singular_values": self.singular_values, "fk_check": self.fk_check,
                         "loads_back": self.loads_back, "warnings": self.warnings,
                         "provenance": self.provenance})


# --------------------------------------------------------------------------- inputs
def model_of_twin(twin: str | Path) -> Path:
    """The directory of a hybrid model with a geometric effect inside a twin directory.

    Parameters
    ----------
    twin : str or Path
        The twin directory.

    Returns
    -------
    Path
    """
    d = Path(twin)
    if not d.is_dir():
        raise DataError(f"{d}: no such twin directory")
    for meta in sorted(d.rglob("hybrid.json")):
        try:
            effects = read_json(meta, "a model file").get("effects", [])
        except (DataError, AttributeError):  # unreadable or not an object: not this twin's map
            continue
        if "geometric" in effects:
            return meta.parent
    raise ModelError(f"{d}: this twin's maps hold no geometric effect; {NO_GEOMETRIC}")


def _recorded(f: FileRecord) -> Path:
    """A file the model's provenance names, still there and unchanged (else DataError)."""
    p = Path(f.path) if Path(f.path).is_absolute() else ROOT / f.path
    if not p.is_file():
        raise DataError(f"the model's training input {f.path} (in its provenance) is gone; "
                        "give --data FILE (the table it was fitted on)")
    if sha256_file(p) != f.sha256:
        raise DataError(f"the model's training input {f.path} changed since the fit (SHA-256 differs); "
                        "give --data FILE (the table it was fitted on)")
    return p


def training_data(model: HybridModel, model_dir: Path, skip_bad: bool = False) -> tuple[Path, Data]:
    """The training data the model's provenance names (hash checked): the first recorded file
    that is not a YAML or a sidecar, read as a measurement table, else through each recorded
    YAML in turn as an import mapping (dt fit records the --mapping it used).

    Parameters
    ----------
    model : HybridModel
        The saved model.
    model_dir : Path
        Its directory.
    skip_bad : bool, optional
        Skip bad rows instead of raising.

    Returns
    -------
    path : Path
    data : Data
    """
    rec: Provenance | None = getattr(model, "provenance_", None)
    files = list(rec.inputs) if rec is not None else []
    data = [f for f in files if not f.path.endswith((".meta.json", ".yaml", ".yml"))]
    if not data:
        raise DataError(f"{model_dir}: the model's provenance names no training data; identifiability needs "
                        "its joint angles: give --data FILE (the table it was fitted on)")
    path = _recorded(data[0])
    try:
        return path, load_data(path, None, skip_bad)
    except DataError as first:
        for f in files:
            if f.path.endswith((".yaml", ".yml")):
                try:
                    return path, load_data(path, _recorded(f), skip_bad)
                except (DataError, ConfigError):
                    continue
        raise DataError(f"{first} (the model's training file; give --data FILE and --mapping YAML)") from first


def _load_model(model_dir: Path) -> tuple[HybridModel, Chain, Path]:
    if not (model_dir / "hybrid.json").is_file():
        raise DataError(f"{model_dir}: no saved model (hybrid.json); train one with dt fit")
    model = HybridModel.load(model_dir)
    if "geometric" not in model.effects:
        raise ModelError(f"{model_dir}: the model holds no geometric effect; {NO_GEOMETRIC}")
    if not isinstance(model.robot, (str, Path)):  # a loaded model names its robot reference (or none)
        raise ModelError(f"{model_dir}: the model names no robot config (its kinematic model)")
    try:
        robot = robots.resolve(model.robot)
    except TwinError as exc:
        raise ModelError(f"{model_dir}: the model's robot config {model.robot} is missing; the export needs "
                         f"the kinematic model it was fitted with ({exc})") from exc
    chain = resolve_chain(robot.text)
    assert chain is not None
    return model, chain, robot.file


# --------------------------------------------------------------------------- export
def export_robot(model_dir: str | Path, fmt: str, out: str | Path, data: str | Path | None = None,
                 mapping: str | Path | None = None, skip_bad: bool = False, rtol: float = ALIAS_RTOL,
                 name: str | None = None, refine_fit: bool = True) -> ExportResult:
    """Write the calibrated robot of a saved model, load it back and check it.

    Only identifiable combinations are exported. The geometric set is complete, hence rank
    deficient (dt_runtime.models.effects.geometric): over a given design several parameters move
    the TCP alike, and the ridge of the fit splits such a combination between them arbitrarily, or
    (a column that is numerically zero) gives a meaningless value. `models.identifiability.aliasing`
    judges this from the geometric block's columns over the training joint angles (angles scaled
    to metres at the TCP by the arm's reach): the rank, and a basis of that many parameters chosen
    in the order joint offsets, frames 1..n, tool. Every other parameter's fitted value is moved
    onto the basis parameters it aliases; it is then listed as not identifiable, with what
    absorbed it, and exported as zero. A parameter whose column is zero is listed as having no
    effect on the TCP over these data.

    Why the training data: identifiability is a property of the design (which joint configurations
    were measured), which the saved model does not keep; but its traceability record names the
    training data file with its SHA-256. So the joint angles come from `data` when given, else from
    the file the record names if it is still there unchanged (checked by hash): an export never
    judges identifiability on other data than the model was fitted on without being told to.

    The check: the geometric effect is linear in its parameters (e = A theta), while the exported
    chain applies them exactly (a joint offset as a rotation of the joint's origin about its axis;
    a frame's translation d and rotation w as Trans(d) Rot(w) of its origin, in its own axes; the
    tool's translation in the flange axes). The calibrated TCP is fk_nominal(q) - A(q) theta; the chain with
    the first-order values differs from it by the model's second-order error
    (`first_order_max_mm`/`first_order_rms_mm`). By default the basis values are refined
    (Gauss-Newton, `refine`) so that the exact chain reaches the calibrated TCP. The written file
    is loaded back and its TCP compared with the calibrated one at the training joint
    configurations, against `FK_TOL_MM`; what remains is the model's prediction along directions
    the export leaves out (`non_identifiable_part_max_mm`).

    Parameters
    ----------
    model_dir : str or Path
        A saved model whose effects include `geometric`.
    fmt : str
        'urdf' or 'dh'.
    out : str or Path
        The file to write.
    data : str or Path, optional
        The training measurements; default the file the model's provenance names.
    mapping : str or Path, optional
        Import mapping for a foreign `data` file.
    skip_bad : bool, optional
        Skip bad rows of the data instead of stopping.
    rtol : float, optional
        Relative singular value below which a direction is not identifiable.
    name : str, optional
        The exported robot's name.
    refine_fit : bool, optional
        False writes the first-order values.

    Returns
    -------
    ExportResult
    """
    if fmt not in FORMATS:
        raise DataError(f"unknown export format {fmt!r}; allowed: {', '.join(FORMATS)}")
    model_dir = Path(model_dir)
    model, chain, robot = _load_model(model_dir)
    if data is not None:
        data_file, d = Path(data), load_data(data, mapping, skip_bad)
    else:
        data_file, d = training_data(model, model_dir, skip_bad)
    ds = d.dataset
    if ds.joints is None:
        raise DataError(f"{data_file}: no joint angle columns q1..q{chain.dof}; the export needs them")
    if ds.joints.shape[1] != chain.dof:
        raise DataError(f"{data_file}: {ds.joints.shape[1]} joint columns, the robot has {chain.dof}")
    q = np.unique(ds.joints, axis=0)
    geo = [(k, nm, u) for k, (eff, nm, u, _) in enumerate(model.param_names_) if eff == "geometric"]
    theta = np.array([model.theta_[k] for k, _, _ in geo])
    u_theta = np.array([model.theta_u_[k] for k, _, _ in geo])
    block = Geometric().build(Inputs(chain.fk(q), joints=q), chain)
    names = tuple(nm for _, nm, _ in geo)
    if block.names != names:
        raise ModelError(f"{model_dir}: the model's geometric parameters do not match its robot config's chain")
    units = tuple(u for _, _, u in geo)
    reach = float(np.sqrt(np.mean(np.sum((chain.fk(q) - chain.frames(q)[0][:, 0]) ** 2, axis=1))))
    ident = aliasing(block.A, names, units, max(reach, 1e-3), rtol)
    theta_x = ident.combine(theta)
    calibrated = chain.fk(q) - np.einsum("nap,p->na", block.A, theta)
    first = calibrated_chain(chain, _values(names, theta_x))
    first_diff = np.linalg.norm(first.fk(q) - calibrated, axis=1) * MM_PER_M
    theta_r = refine(chain, names, theta_x, ident.basis, q, calibrated) if refine_fit else theta_x
    cal = calibrated_chain(chain, _values(names, theta_r))

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    robot_name = name or f"{chain.name}_calibrated"
    header = _header(model_dir, data_file, ident, names, theta_r)
    warnings: list[str] = []
    if fmt == "urdf":
        out.write_text(urdf_text(cal, robot_name, header))
        ET.parse(out)  # an XML parser that knows nothing of ours
        back = chain_from_urdf(out)
        loads = {"xml.etree": True, "chain_from_urdf": True}
    else:
        table = dh_table(cal)
        out.write_text(table.yaml_text(robot_name, chain.gear_harmonics, header))
        back = load_robot(out)
        loads = {"load_robot": True}
        if table.long_rows:
            warnings.append(f"DH rows {', '.join(map(str, table.long_rows))}: nearly parallel axes give "
                            "|d| or |a| over ten times the reach (standard DH's singularity; the table is "
                            "still exact, the URDF export has no such rows)")

    diff = np.linalg.norm(back.fk(q) - calibrated, axis=1) * MM_PER_M
    zero = np.zeros_like(theta)
    zero[list(ident.no_effect)] = theta[list(ident.no_effect)]
    dropped = np.linalg.norm(np.einsum("nap,p->na", block.A, theta - theta_x), axis=1) * MM_PER_M
    dropped_zero = np.linalg.norm(np.einsum("nap,p->na", block.A, zero), axis=1) * MM_PER_M
    fk = {"n_points": int(len(q)), "max_mm": float(diff.max()), "rms_mm": float(np.sqrt(np.mean(diff ** 2))),
          "tolerance_mm": FK_TOL_MM, "ok": bool(diff.max() < FK_TOL_MM), "refined": refine_fit,
          "first_order_max_mm": float(first_diff.max()),
          "first_order_rms_mm": float(np.sqrt(np.mean(first_diff ** 2))),
          "non_identifiable_part_max_mm": float(dropped.max()),
          "no_effect_part_max_mm": float(dropped_zero.max()),
          "correction_rms_mm": float(np.sqrt(np.mean(np.sum((calibrated - chain.fk(q)) ** 2, axis=1)))
                                     * MM_PER_M)}
    if not fk["ok"]:
        warnings.append(f"the exported FK differs from the calibrated FK by up to {fk['max_mm']:.4f} mm "
                        f"(> {FK_TOL_MM} mm), of which up to {fk['non_identifiable_part_max_mm']:.4f} mm is the "
                        "model's prediction along directions the data cannot identify (up to "
                        f"{fk['no_effect_part_max_mm']:.4f} mm from parameters with no effect, fitted to rounding "
                        "noise), which the export leaves out")
    exported = [{"name": names[i], "unit": units[i], "value": float(theta_r[i]), "first_order": float(theta_x[i]),
                 "fitted": float(theta[i]),
                 "u": float(u_theta[i]), "absorbs": sorted(names[j] for j, c in ident.aliases.items() if i in c)}
                for i in ident.basis]
    not_id = [{"name": names[j], "unit": units[j], "fitted": float(theta[j]),
               "absorbed_by": {names[i]: c for i, c in coefs.items()}} for j, coefs in sorted(ident.aliases.items())]
    prov = build([data_file, *files_under(model_dir)], robot=robot)
    return ExportResult(str(out), fmt, str(model_dir), model.robot_, str(data_file), int(len(q)), len(names),
                        ident.rank, exported, not_id, [names[j] for j in ident.no_effect], ident.groups(),
                        list(ident.singular_values), fk, loads, warnings, prov)


def _header(model_dir: Path, data_file: Path, ident: Aliasing, names: tuple[str, ...],
            theta_x: np.ndarray) -> str:
    basis = ", ".join(f"{names[i]}={theta_x[i]:.6g} {ident.units[i]}" for i in ident.basis)
    not_id = ", ".join(names[j] for j in sorted(ident.absorbed)) or "none"
    no_eff = ", ".join(names[j] for j in ident.no_effect) or "none"
    return (f"Calibrated by dt export from the model {model_dir} (geometric effect) on the joint angles of "
            f"{data_file}.\nIdentifiable parameters applied ({ident.rank} of {len(names)}): {basis}.\n"
            f"Not identifiable (aliases, moved onto the above): {not_id}.\n"
            f"No effect on the TCP over the data: {no_eff}.")
