"""The software's version and, when run from a git checkout, its commit: every report, model
and summary can say which code produced it."""
from __future__ import annotations

import subprocess
from functools import lru_cache
from importlib import metadata

from dt_runtime.common.paths import ROOT

DIST = "cobot-dt"


@lru_cache(maxsize=1)
def version() -> str:
    """The installed version of the distribution, or "0+unknown" when it is not installed.

    Returns
    -------
    str
    """
    try:
        return metadata.version(DIST)
    except metadata.PackageNotFoundError:
        return "0+unknown"


@lru_cache(maxsize=1)
def git_commit() -> str | None:
    """The checkout's commit (with "-dirty" when files differ), or None outside a git checkout."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return sha + ("-dirty" if dirty else "") if sha else None


def version_string() -> str:
    """The version with the git commit when there is one, e.g. "0.4.0 (commit abc...)".

    Returns
    -------
    str
    """
    c = git_commit()
    return version() + (f" (commit {c})" if c else "")
