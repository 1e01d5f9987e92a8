"""The command line's surface, as a newcomer meets it: the parser loads no heavy library (so
--help, --version and an argument error answer at once), an unknown option is the subcommand's
error, and the commands print a short text unless --json."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from dt_runtime.cli import ack, consume, dashboard, simulate, status
from dt_runtime.cli.main import main

HEAVY = ("numpy", "scipy", "sklearn", "pybullet", "zenoh", "matplotlib", "starlette", "uvicorn", "python_calamine",
         "cv2", "pydantic", "yaml")


def _loaded_after(code: str) -> list[str]:
    probe = (f"import sys\n{code}\n"
             f"print([m for m in {HEAVY!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1].replace("'", '"'))


def test_building_the_parser_imports_no_heavy_library():
    assert _loaded_after("from dt_runtime.cli.main import build_parser\nbuild_parser()") == []


@pytest.mark.parametrize("argv", [["--version"], ["fit", "--help"], ["fit"], ["demo", "--quik"], ["dashboard"]])
def test_help_version_and_argument_errors_import_no_heavy_library(argv):
    code = ("from dt_runtime.cli.main import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass")
    assert _loaded_after(code) == []


def test_an_unknown_option_is_the_subcommands_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--quik"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "dt demo: error: unrecognized arguments: --quik" in err and "usage: dt demo" in err


def test_dashboard_without_anything_to_show_says_what_to_give(capsys):
    assert main(["dashboard"]) == 2
    err = capsys.readouterr().err
    assert "--config" in err and "--results" in err and "--plant" in err and "None" not in err


def _not_json(text: str) -> None:
    with pytest.raises(ValueError):
        json.loads(text)


def test_the_human_texts_are_sentences_not_json():
    sim = {"scenario": "s.yaml", "name": "paper_default", "seed": 7, "effects": {}, "phases": ["doe", "validation"],
           "n": 312, "dropped_rows": 0, "registration_rms_mm": 0.0123, "noise_floor_mm": 0.0301, "out": "out/a.csv"}
    texts = [
        simulate.human(sim),
        ack.human({"action": 3, "kind": "done", "request": 2, "applied": True, "result": "applied: halted -> nominal"}),
        ack.human({"kind": "done", "request": 2, "published": "dt/c/r/maintenance/done/2", "applied": None}),
        dashboard.human({"url": "http://127.0.0.1:8765/", "bus": "dt/c/r", "received": {"telemetry": 5, "health": 1},
                         "bus_refused": 0, "dropped": 0, "metrology": False, "plant": False, "actions": [],
                         "operators": []}),
        consume.human({"requests": 1, "copies": 4, "group": "maintenance"}),
    ]
    for t in texts:
        _not_json(t)
    assert "312 rows" in texts[0] and "out/a.csv" in texts[0]
    assert texts[1].count("applied") == 1


def test_status_says_applied_once():
    assert status._applied("applied: maintenance_requested -> nominal") == "applied: maintenance_requested -> nominal"
    assert status._applied("ignored: the escalation was nominal").startswith("ignored")
    assert status._applied("delivery of 2 copies confirmed") == "applied: delivery of 2 copies confirmed"


def test_paths_are_shown_normalised(tmp_path):
    from dt_runtime.common.paths import beside

    assert str(beside(tmp_path / "configs", "../out/demo/model")) == str(tmp_path / "out" / "demo" / "model")
    assert beside(tmp_path / "configs", "/abs/x") == type(tmp_path)("/abs/x")


def test_the_git_commit_is_asked_for_only_by_version(monkeypatch, capsys):
    from dt_runtime.cli import main as cli_main

    def no_git():
        raise AssertionError("git asked while building the parser")

    monkeypatch.setattr(cli_main, "version_string", no_git)
    args = cli_main.parse(cli_main.build_parser(), ["robots"])
    assert args.cmd == "robots"
    monkeypatch.setattr(cli_main, "version_string", lambda: "9.9 (commit abc)")
    with pytest.raises(SystemExit) as exc:
        cli_main.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out == "dt 9.9 (commit abc)\n"


def test_the_blas_limit_reaches_the_libraries_loaded_after_the_parser():
    # dt limits BLAS to DT_BLAS_THREADS (default 1) without importing numpy first: the limit goes
    # into the variables OpenBLAS reads as it loads
    import os

    code = ("from dt_runtime.common.threads import limit_blas_threads_when_loaded\n"
            "limit_blas_threads_when_loaded()\n"
            "import sys\nassert 'numpy' not in sys.modules\n"
            "import numpy, scipy.linalg\n"
            "from threadpoolctl import threadpool_info\n"
            "print(sorted({i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'}))")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                                            "OMP_NUM_THREADS", "DT_BLAS_THREADS")}
    for want, extra in (([1], {}), ([2], {"DT_BLAS_THREADS": "2"})):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                             env={**env, **extra}).stdout
        assert json.loads(out) == want
