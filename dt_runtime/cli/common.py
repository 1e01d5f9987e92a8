"""What every `dt` command shares: the argument groups for data and output, and the progress
switch. Each command module holds its own arguments, its run and its human text."""
from __future__ import annotations

import argparse
from pathlib import Path

from dt_runtime.common.progress import Progress


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def folds(text: str) -> int:
    """--folds K: an integer >= 2 (one fold leaves nothing to train on).

    Parameters
    ----------
    text : str
        The option's value as typed.

    Returns
    -------
    int

    Raises
    ------
    argparse.ArgumentTypeError
        When it is not an integer or is below 2.
    """
    k = _integer(text)
    if k < 2:
        raise argparse.ArgumentTypeError(f"{k}: cross-validation needs at least 2 folds")
    return k


def seed_number(text: str) -> int:
    """--seed N: a non-negative integer (numpy's generators take no negative seed).

    Parameters
    ----------
    text : str
        The option's value as typed.

    Returns
    -------
    int

    Raises
    ------
    argparse.ArgumentTypeError
        When it is not an integer or is negative.
    """
    n = _integer(text)
    if n < 0:
        raise argparse.ArgumentTypeError(f"{n}: a seed is a non-negative integer (0, 1, 2, ...)")
    return n


def cv_folds(text: str) -> int:
    """--cv K: 0 (no cross-validation) or an integer >= 2.

    Parameters
    ----------
    text : str
        The option's value as typed.

    Returns
    -------
    int

    Raises
    ------
    argparse.ArgumentTypeError
        When it is not an integer, or is 1 or negative.
    """
    k = _integer(text)
    if k != 0 and k < 2:
        raise argparse.ArgumentTypeError(f"{k}: 0 (none) or at least 2 folds")
    return k


STRICT_EXIT = 3  # `--strict` and a validity check that failed (docs/cli.md)


def add_strict_arg(q: argparse.ArgumentParser) -> None:
    """Add ``--strict``: exit STRICT_EXIT (after writing everything) when a validity check fails.

    Parameters
    ----------
    q : argparse.ArgumentParser
    """
    q.add_argument("--strict", action="store_true",
                   help=f"exit {STRICT_EXIT} (after writing everything) when a validity check fails: the stated "
                        "uncertainty does not cover the errors, or Eq. 17 disagrees with it")


def validity_exit(args: argparse.Namespace, summary: dict) -> int:
    """The exit code of a command whose summary carries a ``validity`` block (analysis.validity).

    0, or STRICT_EXIT with ``--strict`` when its status is 'fail'. With ``--json`` the block's line
    also goes to stderr (stdout holds only the JSON object).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.
    summary : dict
        The command's result.

    Returns
    -------
    int
    """
    import logging

    v = summary.get("validity") or {}
    if getattr(args, "json", False) and v.get("status") not in (None, "ok"):
        logging.getLogger("dt.validity").warning("%s", v["line"])
    return STRICT_EXIT if getattr(args, "strict", False) and v.get("status") == "fail" else 0


def add_output_args(q: argparse.ArgumentParser) -> None:
    """Add ``--json`` and ``--no-progress``.

    Parameters
    ----------
    q : argparse.ArgumentParser
    """
    q.add_argument("--json", action="store_true", help="print the result as one JSON object")
    q.add_argument("--no-progress", action="store_true", help="do not show progress on stderr")


ROBOT_HELP = ("the robot's nominal kinematics: a catalogue arm (ur5e, panda, iiwa14, ...: `dt robots` lists them), "
              "a robot config YAML (e.g. configs/robots/ur10.yaml) or a URDF (arm.urdf, arm.urdf#tool0 to end "
              "at link tool0); without a tool offset it is fitted from the data (docs/robots.md). Default: the "
              "import mapping's robot, else configs/robots/cobot_hc20_like.yaml")


def add_data_args(q: argparse.ArgumentParser, kinematics: bool = True) -> None:
    """Add the data options: ``--data``, ``--mapping``, ``--skip-bad``, ``--seed`` and, with
    ``kinematics``, ``--robot`` and ``--gp-inputs``.

    Parameters
    ----------
    q : argparse.ArgumentParser
    kinematics : bool
        Add the kinematics options too.
    """
    q.add_argument("--data", required=True, nargs="+", metavar="FILE",
                   help="measurement table CSV (or a foreign file with --mapping); several files are one campaign, "
                        "each a session (time shifted, points renumbered, a 'session' column)")
    q.add_argument("--mapping", default=None, metavar="YAML",
                   help="import mapping for a foreign file (e.g. configs/import/ur10.yaml)")
    q.add_argument("--skip-bad", action="store_true", help="skip bad rows (each is listed) instead of stopping")
    q.add_argument("--seed", type=seed_number, default=0, help="seed of folds and GP restarts (default 0)")
    if not kinematics:
        return
    q.add_argument("--robot", default=None, metavar="ROBOT", help=ROBOT_HELP)
    q.add_argument("--gp-inputs", default="tcp_speed", choices=("tcp_speed", "tcp", "joints", "none"),
                   help="what the GP on the remaining error sees (default tcp_speed, the paper's)")


def add_effects_file_arg(q: argparse.ArgumentParser) -> None:
    """Add ``--effects-file``: effects of one's own, declared in YAML (docs/effects.md).

    Parameters
    ----------
    q : argparse.ArgumentParser
    """
    q.add_argument("--effects-file", default=None, metavar="YAML",
                   help="effects of your own, declared in YAML as regressors built from the data's columns "
                        "(e.g. configs/effects/humidity.yaml; docs/effects.md): usable in --effects, tested by "
                        "diagnose after the catalogue, kept by a saved model")


def effects_catalogue(args: argparse.Namespace):
    """The command's effects: the catalogue, the installed plugins and --effects-file's declarations.

    Built once per command and passed down; nothing is registered in the process, so one call's
    file does not change what the next call knows.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    models.effects.Catalogue

    Raises
    ------
    TwinError
        When the effects file cannot be read or declares an effect wrongly.
    """
    from dt_runtime.models import effects as fx

    path = getattr(args, "effects_file", None)
    cat = fx.default()
    return cat.with_file(path) if path else cat


#: What a model directory of `dt fit` / `dt diagnose --auto --out` holds: a directory replaced by
#: a new model must have it (common.outputs.staged).
MODEL_MARKS = ("hybrid.json",)


def data_inputs(args: argparse.Namespace) -> list[str]:
    """Every file a data command reads (--data, --mapping, --effects-file, --instruments, --model):
    an output directory that holds one of them is refused (it is replaced whole).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    list of str
    """
    data = args.data if isinstance(args.data, list) else [args.data]
    models = args.model if isinstance(getattr(args, "model", None), list) else [getattr(args, "model", None)]
    return [str(f) for f in (*data, getattr(args, "mapping", None), getattr(args, "effects_file", None),
                             getattr(args, "instruments", None), *models) if f]


def input_files(args: argparse.Namespace) -> list[str]:
    """The files beside the data that shaped the result, for the provenance (hashed): the import
    mapping and the declared effects.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    list of str
    """
    return [f for f in (getattr(args, "mapping", None), getattr(args, "effects_file", None)) if f]


def check_declared(names_: list[str], inp, where: str, path: str, catalogue) -> None:
    """Refuse data that lack a column a declared effect of --effects-file reads.

    The user named the file's effects to test them, so a typo must not pass as 'not testable'.

    Parameters
    ----------
    names_ : list of str
        The declared effects' names.
    inp : models.effects.Inputs
        The data's inputs.
    where : str
        Names the data in the error.
    path : str
        The effects file.
    catalogue : models.effects.Catalogue
        Where the names are looked up (``effects_catalogue``).

    Raises
    ------
    DataError
        Naming the effect, the missing columns and the data's columns.
    """
    from dt_kernel.errors import DataError
    from dt_runtime.models.effects.declared import columns_of

    for name in names_:
        missing = [c if c != "joints" else "q1..qk" for c in catalogue.get(name).columns if not inp.has(c)]
        if missing:
            raise DataError(f"{where}: effect '{name}' (declared in {path}) reads the column(s) {', '.join(missing)}, "
                            f"which the data do not have; their columns: {', '.join(columns_of(inp)) or 'none'}")


def add_session_args(q: argparse.ArgumentParser) -> None:
    """Add the options for a campaign of several sessions (several --data files): ``--exclude-session``,
    ``--reference-session``, ``--session-term``.

    Parameters
    ----------
    q : argparse.ArgumentParser
    """
    q.add_argument("--exclude-session", default="", metavar="NAME,...",
                   help="leave these sessions out (by name, file name or index)")
    q.add_argument("--reference-session", default=None, metavar="NAME",
                   help="the session the session terms are measured against (default the first)")
    q.add_argument("--session-term", default="", metavar="TERM,...",
                   help="fit session terms as nuisance, never deployed (the model predicts the reference session's "
                        "robot): tool (a re-mounted SMR/tool), base (the set-up's rigid part), joints (changed joint "
                        "zeros)")


def add_mpe_arg(q: argparse.ArgumentParser) -> None:
    """Add ``--mpe-mm``: the instrument's maximum permissible error (mm), the noise floor when the data
    state no uncertainty.

    Parameters
    ----------
    q : argparse.ArgumentParser
    """
    q.add_argument("--mpe-mm", type=_positive, default=None, metavar="MM",
                   help="the instrument's maximum permissible error (mm): the noise floor when the data state "
                        "no uncertainty ux..uz")


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (v > 0 and v < 100):
        raise argparse.ArgumentTypeError(f"{v}: a length in mm, > 0 and < 100")
    return v


def names(text: str | None) -> tuple[str, ...]:
    """A comma-separated list of names (effects, model names) as a tuple, blanks dropped.

    Parameters
    ----------
    text : str or None

    Returns
    -------
    tuple of str
        Empty for None or an empty string.
    """
    return tuple(e.strip() for e in text.split(",") if e.strip()) if text else ()


def progress(args: argparse.Namespace) -> Progress:
    """The progress display on stderr, off with ``--no-progress``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    Progress
    """
    return Progress(enabled=not getattr(args, "no_progress", False))


def load(args: argparse.Namespace, catalogue):
    """The --data file(s) (through --mapping if given), several files as the sessions of one campaign.

    The effects --effects-file declared into ``catalogue`` must find their columns in it; --mpe-mm
    goes into the data's facts.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.
    catalogue : models.effects.Catalogue
        The command's effects (``effects_catalogue``).

    Returns
    -------
    analysis.data.Data

    Raises
    ------
    DataError
        When a file cannot be read or a declared effect lacks its columns.
    """
    from dt_runtime.analysis.data import load_data
    from dt_runtime.models import effects as fx

    declared = list(catalogue.own) if getattr(args, "effects_file", None) else []

    files = args.data if isinstance(args.data, list) else [args.data]
    robot = getattr(args, "robot", None)  # joints-only files: their commanded TCP is its forward kinematics
    if len(files) == 1:
        d = load_data(files[0], args.mapping, args.skip_bad, robot)
    else:
        from dt_runtime.analysis.data import Data
        from dt_runtime.measurements.dataset import sessions
        from dt_runtime.measurements.session_paths import session_names

        each = [load_data(f, args.mapping, args.skip_bad, robot) for f in files]
        ds = sessions([e.dataset for e in each])
        # session i of the 'session' column is session_files[i]; its name tells files of one name apart
        d = Data(ds, {"data": list(files), "n": ds.n,
                      "session_files": [{"file": str(f), "name": name, "rows": e.dataset.n}
                                        | {k: v for k, v in e.info.items() if k in ("registration", "skipped_rows")}
                                        for f, name, e in zip(files, session_names(files), each)]}
                 | ({"robot": each[0].info["robot"]} if "robot" in each[0].info else {}))
    if getattr(args, "mpe_mm", None) is not None:
        d.info["mpe_mm"] = args.mpe_mm
    if declared:
        check_declared(declared, fx.Inputs.of(d.dataset), ", ".join(map(str, files)), args.effects_file, catalogue)
        d.info["declared_effects"] = {"file": str(args.effects_file), "effects": declared}
    return d


def robot_of(args: argparse.Namespace, d) -> str:
    """The robot of the analysis as a reference (``frames.robots``).

    --robot, else the import mapping's ``robot:``, else the default. A robot without a tool offset
    (a catalogue arm, a bare URDF) gets the one the data give (``frames.tool_fit``): the import's fit
    from the measured positions, else a fit from the commanded TCP; it is stated on stderr and in
    the result's ``tool_offset`` and travels in the reference ('?tool_mm=').

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.
    d : analysis.data.Data
        The loaded data (its facts are updated).

    Returns
    -------
    str
        The robot reference.

    Raises
    ------
    TwinError
        When the robot cannot be resolved or its joints do not explain the commanded TCP.
    """
    import logging

    from dt_runtime.analysis.data import DEFAULT_ROBOT
    from dt_runtime.frames import robots
    from dt_runtime.frames.tool_fit import fit_tool
    from dt_runtime.measurements.checks import joints_vs_commanded

    ref = robots.resolve(args.robot or d.info.get("robot") or DEFAULT_ROBOT, [Path.cwd()])
    chain = robots.load(ref)
    q = d.dataset.joints
    if chain.tool_given or q is None or q.shape[1] != chain.dof:
        return _used(d, ref.text)
    # the nominal chain first: do the joints explain the commanded TCP with some tool at all?
    joints_vs_commanded(q, d.dataset.commanded, chain, d.dataset.source, free_tool=True)
    fit = fit_tool(chain, q, d.dataset.commanded, "commanded")
    imported = (d.info.get("registration") or {}).get("tool_offset")
    d.info["tool_offset"] = imported or fit.to_dict()
    log = logging.getLogger("dt.robot")
    log.info("%s gives no tool offset: %s", ref.text, fit.line() if imported is None else
             f"the import's: {imported['xyz_mm']} mm +/- {imported['u_mm']} mm, residual 3D RMS "
             f"{imported['residual_rms_mm']:.3f} mm ({imported['n']} rows)")
    note = fit.note() if imported is None else ""
    if note:
        log.warning("%s", note)
    if fit.residual_rms > 1e-3 and not fit.undetermined:
        log.warning("the commanded TCP departs from %s's nominal kinematics plus one tool offset by %.3f mm RMS: "
                    "another robot, or joints in another order or zero?", ref.text, fit.residual_rms * 1e3)
    return _used(d, ref.with_tool(fit.offset).text)


def _used(d, ref: str) -> str:
    """The data's facts name the robot the analysis uses (the mapping's `robot:` was a default)."""
    if "robot" in d.info:
        d.info["robot"] = ref
    return ref


def parameter_line(p: dict) -> str:
    """One effect parameter for the human summary: value +/- u unit, or why it has no value.

    Parameters
    ----------
    p : dict
        A parameter of a model's ``parameters``.

    Returns
    -------
    str
    """
    from dt_runtime.models.hybrid import unidentified

    if "choice" in p:
        return f"  {p['effect']}.{p['name']}: {p['choice']}" + ("" if p["identified"] else
                                                                 " (the data prefer neither)")
    if p["value"] is None:
        return f"  {p['effect']}.{p['name']}: {unidentified(p)}"
    return f"  {p['effect']}.{p['name']} = {p['value']:.6g} +/- {p['u']:.2g} {p['unit']}" + (
        f" (profile likelihood, interval {p['interval'][0]:.4g}..{p['interval'][1]:.4g})" if "interval" in p else "")


def parameter_lines(parameters: list[dict], base: dict | None) -> list[str]:
    """A model's effect parameters for the human summary: the short base-parameter table
    (reports.parameter_table; for a model saved before base parameters were kept (``base`` None),
    its identified parameters).

    Parameters
    ----------
    parameters : list of dict
    base : dict or None

    Returns
    -------
    list of str
    """
    from dt_runtime.reports.parameter_table import parameter_table, text

    return text(parameter_table(parameters, base)) if parameters else []
