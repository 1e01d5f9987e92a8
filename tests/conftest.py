"""Suite-wide setup: BLAS on one thread, as the `dt` command line runs (dt_runtime.common.threads),
and the diagnosis in this process (DT_WORKERS=1: `dt diagnose` called in process would otherwise
start a worker per core; tests/integration/test_diagnose_parallel.py checks the workers on their own)."""
import os

from dt_runtime.common.threads import limit_blas_threads

limit_blas_threads()
os.environ.setdefault("DT_WORKERS", "1")

# The bus key (dt_runtime.fabric.auth) lives in the user's config directory: the suite gets
# its own (daemons, consumers and `dt` subprocesses share it, as the service's user would), and
# never reads or writes the developer's ~/.config/cobot-dt.
import atexit  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402

_config_home = tempfile.mkdtemp(prefix="dt-tests-config-")
os.environ["XDG_CONFIG_HOME"] = _config_home
atexit.register(shutil.rmtree, _config_home, True)


import contextlib  # noqa: E402
import io  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory):
    """`dt demo --quick --json` once per session: (exit code, stdout, output directory)."""
    from dt_runtime.cli.main import main

    out = tmp_path_factory.mktemp("demo")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["demo", "--quick", "--json", "--no-progress", "--out", str(out)])
    return rc, buf.getvalue(), out


@pytest.fixture(scope="session")
def twin_dir(quick_demo):
    """The quick demo's twin (DIR/model), the one twin the service and bus tests run; read only."""
    rc, _, out = quick_demo
    assert rc == 0
    return out / "model"


@pytest.fixture(scope="session")
def ur_natnet_cell():
    """`python -m emulators.emulated_cell` (UR, NatNet, serial tracker over one plant), 20x faster
    than real time, for the session's end-to-end tests."""
    from tests.support.emulated_cell_process import cell_process

    with cell_process("--time-scale", "0.05", "--seed", "1") as cell:
        yield cell


@pytest.fixture(scope="session")
def ur_natnet_campaign(ur_natnet_cell, tmp_path_factory):
    """`dt campaign` through the emulated cell (registration + 60 DOE rows): (exit code, its
    JSON, a runtime YAML whose twin it is)."""
    from tests.support.emulated_cell_process import campaign

    return campaign(ur_natnet_cell, tmp_path_factory.mktemp("ur_natnet"))
