"""Suite-wide setup: BLAS on one thread, as the `dt` command line runs (dt_runtime.common.threads)."""
from dt_runtime.common.threads import limit_blas_threads

limit_blas_threads()


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
