"""Where the project's shipped configs and data live (a fresh clone needs nothing else)."""
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
DATA = ROOT / "dt_runtime" / "data"


def beside(base: Path, rel: str | Path) -> Path:
    """`rel` as a config names it: absolute as it is, else taken from `base` (the config's
    directory), normalised for messages and output (configs/../out/demo/model is out/demo/model).

    Parameters
    ----------
    base : Path
        The directory relative paths are taken from.
    rel : str or Path
        The path as written.

    Returns
    -------
    Path

    Notes
    -----
    Normalised by text (os.path.normpath), not resolved: a symlinked directory is kept as named.
    """
    p = Path(rel)
    return Path(os.path.normpath(p if p.is_absolute() else Path(base) / p))
