"""Bounded parsing (issue 22, item 8): every file and request the project parses is refused with a
named cause when it is too large, too deep, binary, non-finite or an alias bomb; bounded in time
and memory; never a traceback (exit 1) or a hang. Sizes of model members: tests/unit/test_bounded_inputs.py."""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from dt_kernel.config import MAX_YAML_DEPTH, MAX_YAML_NODES, read_yaml
from dt_kernel.errors import MAX_MESSAGE_CHARS, ConfigError, DataError, ModelError
from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS
from dt_runtime.common.safe_json import loads
from dt_runtime.measurements.dataset import Dataset, write_table
from dt_runtime.models.hybrid import HybridModel
from dt_runtime.twin.twin import Twin

# Nine aliases of nine aliases ... eight times: 380 bytes that expand to 9^8 = 43 million strings.
BOMB = "[" + ", ".join(["&l0 [a, a, a, a, a, a, a, a, a]"] + [
    f"&l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 9)]) + "]"
BINARY = bytes(range(256)) * 16
DEEP = "a: " + "[" * 100_000 + "]" * 100_000 + "\n"


def run_dt(*argv: str) -> tuple[int, dict]:
    """`dt ... --json` in process: (exit code, the JSON object it printed)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main([*argv, "--json"])
    return rc, json.loads(buf.getvalue())


def bounded(fn):
    """(result or the exception raised, CPU seconds, peak MB allocated) of fn()."""
    tracemalloc.start()
    t0 = time.process_time()
    try:
        out = fn()
    except Exception as exc:  # noqa: BLE001 - returned for the caller to check
        out = exc
    cpu = time.process_time() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2 ** 20
    tracemalloc.stop()
    return out, cpu, peak


# --- YAML: one bounded loader (dt_kernel.config.read_yaml) -----------------------------------------
def test_an_alias_bomb_is_refused_while_it_is_read(tmp_path):
    f = tmp_path / "bus.yaml"
    f.write_text(f"cell: c1\nconsumer_groups: {BOMB}\n")
    err, cpu, peak = bounded(lambda: read_yaml(f))
    assert isinstance(err, ConfigError) and "alias bomb" in str(err) and str(f) in str(err)
    # before: 1.05 GB, 13-44 s and a 312 MB message; the budget stops it after 10^5 values
    assert cpu < 2.0 and peak < 50 and len(str(err)) < 400


def test_aliases_within_the_budget_still_work(tmp_path):
    f = tmp_path / "a.yaml"
    f.write_text("base: &b {x: 1, y: [2, 3]}\none: *b\ntwo: {<<: *b, z: 4}\n")
    assert read_yaml(f) == {"base": {"x": 1, "y": [2, 3]}, "one": {"x": 1, "y": [2, 3]},
                            "two": {"x": 1, "y": [2, 3], "z": 4}}
    f.write_text("a: [" + ", ".join(["1"] * 10_000) + "]\n")  # 100 times a large config
    assert len(read_yaml(f)["a"]) == 10_000 < MAX_YAML_NODES


@pytest.mark.parametrize("text, cause", [
    (DEEP, "nested deeper than 32 levels"),
    ("a: " + "{b: " * 40 + "1" + "}" * 40 + "\n", "nested deeper than 32 levels"),
    # 8 levels, repeated 5 times through aliases: 40 levels once expanded
    ("".join(f"l{i}: &l{i} [[[[[[[[{f'*l{i - 1}' if i else 1}]]]]]]]]\n" for i in range(5)), "aliases expanded"),
    ("a: &a [1, *a]\n", "recursive alias"),
])
def test_deep_or_recursive_yaml_is_refused_with_its_line(tmp_path, text, cause):
    f = tmp_path / "deep.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=cause) as ei:
        read_yaml(f)
    assert "at line" in str(ei.value) and MAX_YAML_DEPTH == 32


@pytest.mark.parametrize("content, cause", [
    (BINARY, "a binary file \\(a NUL byte at offset 0\\)"),
    ("speed: caf\xe9\n".encode("latin-1"), "not UTF-8 text \\(byte 0xe9 at offset 10\\)"),
    (b"a: [" + b"1, " * 400_000 + b"1]\n", "more than 1048576 bytes"),
])
def test_binary_or_oversized_yaml_is_refused_by_name(tmp_path, content, cause):
    f = tmp_path / "c.yaml"
    f.write_bytes(content)
    with pytest.raises(ConfigError, match=cause):
        read_yaml(f)


def test_a_device_is_read_no_further_than_the_cap():
    err, cpu, peak = bounded(lambda: read_yaml("/dev/zero"))
    assert isinstance(err, ConfigError) and "more than 1048576 bytes" in str(err)
    assert cpu < 2.0 and peak < 10


@pytest.fixture(scope="module")
def data_and_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("bp")
    rng = np.random.default_rng(0)
    P = rng.uniform([0.6, -0.3, 0.3], [1.2, 0.3, 0.8], (60, 3))
    ds = Dataset(commanded=P, error=1e-4 * np.sin(P * 5) + rng.normal(0, 1e-5, (60, 3)), speed=np.full(60, 0.2))
    csv = write_table(ds, d / "d.csv")
    model = HybridModel(("dynamic",), "tcp").fit(ds, thetas=[np.zeros(5)] * 3).save(d / "m")  # 2 parameters
    return csv, model


@pytest.mark.parametrize("kind", ["bomb", "binary", "deep"])
@pytest.mark.parametrize("option", ["--instruments", "--mapping", "--effects-file"])
def test_bad_yaml_for_the_command_line_options_exits_2_naming_it(data_and_model, tmp_path, option, kind):
    csv, model = data_and_model
    f = tmp_path / f"{kind}.yaml"
    if kind == "bomb":  # under a key each file has
        key = {"--instruments": "instruments", "--mapping": "columns", "--effects-file": "effects"}[option]
        f.write_text(f"{key}: {BOMB}\n")
    else:
        f.write_bytes(BINARY if kind == "binary" else DEEP.encode())
    argv = (["compare", "--model", str(model)] if option == "--instruments" else
            ["fit", "--gp-inputs", "tcp", "--out", str(tmp_path / "m"), "--no-progress"])
    rc, out = run_dt(*argv, "--data", str(csv), option, str(f))
    assert rc == 2 and out["type"] == "ConfigError" and str(f) in out["error"]
    assert {"bomb": "alias bomb", "binary": "binary file", "deep": "nested deeper"}[kind] in out["error"]
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("content", [BINARY, f"bus: {{cell: c1, consumer_groups: {BOMB}}}\n".encode()])
def test_dt_run_refuses_a_binary_or_bombed_runtime_yaml(tmp_path, content):
    f = tmp_path / "runtime.yaml"
    f.write_bytes(content)
    rc, out = run_dt("run", "--config", str(f))
    assert rc == 2 and out["type"] == "ConfigError" and str(f) in out["error"]
    assert not (tmp_path / "out").exists()


def test_a_message_quoting_a_huge_value_is_cut():
    value = [["a"] * 9] * 10 ** 6  # what an expanded bomb would hand to the message
    err = ConfigError("f.yaml", "bus.consumer_groups", value, "a list of group names")
    assert len(str(err)) < 500 and "a list of group names" in str(err)
    assert "<an integer of 5001 digits>" in str(ConfigError("f.yaml", "k", 10 ** 5000, "a number"))
    long = DataError("x" * 10 ** 6)
    assert len(str(long)) < MAX_MESSAGE_CHARS + 100 and str(long).endswith("[998000 more characters not shown]")


# --- model and twin files: JSON + NPZ, bounded and finite ------------------------------------------
@pytest.mark.parametrize("raw, cause", [
    (b'{"a": ' + b"7" * 5000 + b"}", "an integer of 5000 digits"),
    (b"[" * 200_000 + b"]" * 200_000, "nested deeper than 32 levels"),
    (b"[" * 40 + b"]" * 40, "nested deeper than 32 levels \\(at 0.0.0"),
    (b'{"u": [1, Infinity]}', "u.1 is inf"),
    (b'{"dof": [1, -Infinity]}', "dof.1 is -inf"),
    (b'{"dof": NaN}', "dof is nan"),
    (b'{"a": 1e999}', "a is inf"),
    (b"\xff\xfe{}", "not UTF-8 text \\(byte 0xff at offset 0\\)"),
    (b"{'a': 1}", "not JSON"),
    (b" " * 1001, "1001 bytes, more than the 1000 allowed"),
])
def test_the_json_reader_refuses_with_the_cause_and_the_key(raw, cause):
    with pytest.raises(DataError, match=f"^src: {cause}"):
        loads(raw, "src", max_bytes=1000 if len(raw) < 2000 else 10 ** 6, infinite_ok=("dof",))
    assert loads(b'{"u": {"dof": [Infinity, 3]}, "n": -12345678901234567890}', "src", max_bytes=100,
                 infinite_ok=("dof",)) == {"u": {"dof": [float("inf"), 3]}, "n": -12345678901234567890}

def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _edit_npz(path: Path, **change) -> None:
    with np.load(path) as z:
        arrays = {k: z[k].copy() for k in z.files}
    for k, fn in change.items():
        arrays[k] = fn(arrays[k])
    np.savez(path, **arrays)


def _edit_json(path: Path, fn) -> None:
    meta = json.loads(path.read_text())
    fn(meta)
    # allow_nan: NaN and Infinity written as a careless tool would; "SEED" becomes 10^5000
    path.write_text(json.dumps(meta).replace('"SEED"', "1" + "0" * 5000))


def _poison(a: np.ndarray, value: float = np.inf) -> np.ndarray:
    a.flat[0] = value
    return a


@pytest.mark.parametrize("edit, named", [
    (lambda d: _edit_npz(d / "gp.npz", Q_1=_poison), "gp.npz: member 'Q_1.npy' holds 1 NaN or infinite"),
    (lambda d: _edit_npz(d / "hybrid.npz", theta_u=lambda a: np.full(2, np.nan)), "member 'theta_u.npy' holds 2"),
    (lambda d: _edit_json(d / "gp.json", lambda m: m["models"][0].update(noise_var_=float("nan"))),
     "gp.json: models.0.noise_var_ is nan"),
    (lambda d: _edit_json(d / "gp.json", lambda m: m["models"][2]["theta"].__setitem__(1, float("nan"))),
     "gp.json: models.2.theta.1 is nan"),
    (lambda d: _edit_json(d / "hybrid.json", lambda m: m.update(residual_rms_m=float("inf"))),
     "hybrid.json: residual_rms_m is inf"),
    (lambda d: _edit_npz(d / "gp.npz", alpha_0=lambda a: a[: len(a) // 2]), "output 0: arrays of disagreeing shapes"),
    (lambda d: (d / "gp.npz").write_bytes((d / "gp.npz").read_bytes()[:3000]), "gp.npz: not a readable NPZ file"),
    (lambda d: _edit_npz(d / "hybrid.npz", theta=lambda a: np.zeros(7)), "do not fit the 2 parameters"),
    (lambda d: (d / "hybrid.json").write_text('{"a": ' + "[" * 200_000 + "]" * 200_000 + "}"),
     "hybrid.json: nested deeper than 32 levels"),
    (lambda d: (d / "hybrid.json").write_bytes(BINARY), "hybrid.json: not UTF-8 text"),
    (lambda d: _edit_json(d / "hybrid.json", lambda m: m.update(seed="SEED")), "an integer of 5001 digits"),
    (lambda d: _edit_json(d / "hybrid.json", lambda m: m.pop("param_names")), "a missing or malformed entry"),
])
def test_a_non_finite_cut_or_malformed_model_is_refused_at_load_naming_file_and_member(data_and_model, tmp_path,
                                                                                      edit, named):
    d = _copy(data_and_model[1], tmp_path / "m")
    edit(d)
    with pytest.raises((ModelError, DataError), match=named):
        HybridModel.load(d)


def _runtime_yaml(tmp_path: Path, twin: Path) -> Path:
    f = tmp_path / "runtime.yaml"
    f.write_text(json.dumps({  # JSON is YAML
        "twin": str(twin), "store": str(tmp_path / "store" / "dt.sqlite"), "realtime": False, "publish": False,
        "sim": {"scenario": str(CONFIGS / "scenarios" / "paper_default.yaml"), "cell": str(CONFIGS / "cell.yaml")}}))
    return f


def test_a_stated_uncertainty_of_inf_is_refused_and_an_infinite_dof_is_not(twin_dir, tmp_path):
    d = _copy(twin_dir, tmp_path / "t")
    _edit_json(d / "twin.json", lambda m: m["u"]["eq13_e_lt_hat"]["dof"].__setitem__(2, float("inf")))
    assert np.isinf(Twin.load(d).uncertainty.e_lt_hat.dof[2])  # GUM: infinite degrees of freedom
    _edit_json(d / "twin.json", lambda m: m["u"]["eq11_tcp_c"]["U"].__setitem__(0, float("inf")))
    with pytest.raises(ModelError, match=r"twin.json: u.eq11_tcp_c.U.0 is inf"):
        Twin.load(d)
    _edit_json(d / "twin.json", lambda m: m["u"]["eq11_tcp_c"].update(U=[1e-4, 1e-4, 1e-4], dof=[float("nan")] * 3))
    with pytest.raises(ModelError, match=r"u.eq11_tcp_c.dof.\d is nan"):
        Twin.load(d)


def test_dt_run_with_a_nan_model_exits_2_and_opens_nothing(twin_dir, tmp_path):
    d = _copy(twin_dir, tmp_path / "t")
    _edit_json(d / "e_lt" / "gp.json", lambda m: m["models"][1].update(noise_var_=float("nan")))
    rc, out = run_dt("run", "--config", str(_runtime_yaml(tmp_path, d)), "--duration", "1")
    assert rc == 2 and "e_lt/gp.json: models.1.noise_var_ is nan" in out["error"]
    assert not (tmp_path / "store").exists()


@pytest.mark.parametrize("member", ["/dev/zero", "fifo"])
def test_a_model_member_that_never_ends_is_refused_within_seconds(twin_dir, tmp_path, member):
    """Before: `dt run` read e_lt/gp.npz -> /dev/zero for ever (10 GB RSS in 20 s). A subprocess
    with a timeout: a hang fails the test instead of the suite."""
    d = _copy(twin_dir, tmp_path / "t")
    npz = d / "e_lt" / "gp.npz"
    npz.unlink()
    os.symlink("/dev/zero", npz) if member == "/dev/zero" else os.mkfifo(npz)
    p = subprocess.run([sys.executable, "-m", "dt_runtime.cli.main", "run", "--config",
                        str(_runtime_yaml(tmp_path, d)), "--duration", "1"],
                       capture_output=True, text=True, timeout=120)
    kind = "a character device" if member == "/dev/zero" else "a FIFO (named pipe)"
    assert p.returncode == 2 and f"{npz}: {kind}, not a regular file" in p.stderr, p.stderr[-2000:]
    assert "Traceback" not in p.stderr and not (tmp_path / "store").exists()


# --- the bus `correct` service: every request answered, bounded --------------------------------------
@pytest.fixture(scope="module")
def correct_service(twin_dir):
    """A CorrectionServer and a client on Zenoh over loopback (as tests/integration/test_bus_correct.py)."""
    from dt_runtime.fabric import BusConfig
    from dt_runtime.fabric.session import close_session, open_session
    from dt_runtime.service.correction_server import CorrectionServer
    from dt_runtime.twin.bounds import Guard, Limits
    from tests.support.loopback import free_port

    port = free_port()
    cfg = BusConfig(cell="c9", robot="r9", listen=[f"tcp/127.0.0.1:{port}"])
    server = CorrectionServer(Guard(Twin.load(twin_dir), Limits()), cfg)
    client = open_session(BusConfig(cell="c9", robot="prog", listen=[f"tcp/127.0.0.1:{free_port()}"],
                                    connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        for _ in range(40):  # the first query may go out before the peers have met
            if list(client.get(cfg.key("correct"), payload=GOOD, timeout=1.0)):
                break
        else:
            raise AssertionError("no reply from the correction server")
        yield server, client, cfg.key("correct")
    finally:
        close_session(client, 3.0)
        assert server.close(3.0)


GOOD = b'{"id": "p1", "target_mm": [900.0, 0.0, 550.0], "speed_mm_s": 500.0}'


def _ask(client, key: str, raw: bytes) -> tuple[dict | None, dict | None, int]:
    """(ok reply, error reply, bytes of the reply) to one raw payload; a generous timeout: no
    reply at all is the failure looked for (the service used to stay silent)."""
    replies = list(client.get(key, payload=raw, timeout=10.0))
    assert len(replies) == 1, f"{len(replies)} replies to {raw[:80]!r}"
    r = replies[0]
    body = (r.ok or r.err).payload.to_bytes()
    return (json.loads(body), None, len(body)) if r.ok is not None else (None, json.loads(body), len(body))


@pytest.mark.parametrize("raw, cause", [
    # the inputs that went unanswered, and the 10 MB that was echoed: refused by their size
    (b'{"target_mm": [900, 0, 550], "speed_mm_s": ' + b"9" * 5000 + b"}", "5044 bytes, more than the 4096 allowed"),
    (b'{"id": ' + b"[" * 100_000 + b"]" * 100_000 + b', "target_mm": [900, 0, 550], "speed_mm_s": 500}',
     "200055 bytes, more than the 4096 allowed"),
    (b'{"id": "' + b"x" * 10 * 2 ** 20 + b'", "target_mm": [900, 0, 550], "speed_mm_s": 500}',
     "10485817 bytes, more than the 4096 allowed"),
    # within the size: by what they hold
    (b'{"target_mm": [900, 0, 550], "speed_mm_s": ' + b"9" * 50 + b"}", "an integer of 50 digits"),
    (b'{"id": ' + b"[" * 1500 + b"]" * 1500 + b', "target_mm": [900, 0, 550], "speed_mm_s": 500}',
     "nested deeper than 8 levels"),
    (b'{"target_mm": [900, 0, 550], "speed_mm_s": 500, "temperature_c": 1e6}',
     r"temperature_c must be a number in \[-50, 150\] deg C, got 1000000.0"),
    (b'{"target_mm": [900, 0, 550], "speed_mm_s": 500, "payload_kg": true}', "payload_kg must be a number"),
    (b'{"target_mm": [true, 0, 550], "speed_mm_s": 500}', r"target_mm \[True, 0, 550\] is not a finite 3-vector"),
    (b'{"target_mm": [900, 0, 550], "speed_mm_s": true}', "speed_mm_s must be a number"),
    (b'{"target_mm": [900, 0, 550], "speed_mm_s": 500, "temperature": 25}', "unknown key.*'temperature'"),
    (b'{"target_mm": [900, NaN, 550], "speed_mm_s": 500}', "target_mm.1 is nan"),
    (b"\xff\xfe", "not UTF-8 text"),
])
def test_every_bad_request_gets_an_error_reply_naming_the_cause(correct_service, raw, cause):
    server, client, key = correct_service
    refused = server.refused
    ok, err, size = _ask(client, key, raw)
    assert ok is None and err["type"] == "DataError" and re.search(cause, err["error"]), err
    assert size < 1000 and server.refused == refused + 1  # nothing of a large request echoed
    ok, err, _ = _ask(client, key, GOOD)
    assert err is None and ok["id"] == "p1" and ok["inside"]  # still serving


def test_a_defect_behind_the_service_still_gets_a_reply(correct_service, monkeypatch):
    server, client, key = correct_service

    def broken(*a):
        raise RuntimeError("a defect")

    monkeypatch.setattr(server, "corrector", broken)
    ok, err, _ = _ask(client, key, GOOD)
    assert ok is None and err == {"id": "p1", "error": "internal error: a defect", "type": "RuntimeError"}


# --- CSV: blank leading lines ignored, lines bounded -----------------------------------------------
def test_blank_leading_lines_are_ignored_as_documented_and_lines_keep_their_numbers(data_and_model, tmp_path):
    from dt_runtime.measurements.dataset import read_table

    csv, _ = data_and_model
    text = csv.read_text()
    f = tmp_path / "blank.csv"
    f.write_text("\n  \n\n" + text)
    assert len(read_table(f)) == len(read_table(csv)) == 60
    lines = text.splitlines()
    lines[4] = lines[4].rsplit(",", 1)[0] + ",abc"  # data row 4, the last column
    f.write_text("\n  \n\n" + "\n".join(lines) + "\n")
    with pytest.raises(DataError, match=f"{f}: line 8: column 'ez': value 'abc'"):  # 3 blank + header + 4
        read_table(f)


@pytest.mark.parametrize("content, cause", [
    ("\n\n" + "x," * 500_000 + "z\n1,2\n", "line 3: a header line of more than 65536 characters"),
    ("x,y,z,speed,ex,ey,ez\n" + "1," * 3_000_000, "line 2: a line of more than 1048576 characters"),
])
def test_an_overlong_header_or_line_is_refused_without_reading_it_whole(tmp_path, content, cause):
    f = tmp_path / "long.csv"
    f.write_text(content)
    rc, out = run_dt("fit", "--data", str(f), "--out", str(tmp_path / "m"), "--no-progress")
    assert rc == 2 and cause in out["error"] and not (tmp_path / "m").exists()
    from dt_runtime.measurements.dataset import read_table

    err, cpu, peak = bounded(lambda: read_table(f))
    assert isinstance(err, DataError) and cause in str(err) and peak < 4  # MB, of a 1-6 MB file: ~2 MB
