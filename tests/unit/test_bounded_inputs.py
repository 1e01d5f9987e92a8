"""Bounded sizes and finite numbers at the boundaries: model files (NPZ), training data, plans
(issue: unbounded growth and sizes)."""
from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest

from dt_kernel.errors import ConfigError, DataError
from dt_runtime.cli.main import main
from dt_runtime.common.safe_npz import load_npz
from dt_runtime.measurements.dataset import Dataset, write_table
from dt_runtime.measurements.plans import PlanConfig
from dt_runtime.models.hybrid import HybridModel


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    return buf.getvalue()


def _model(tmp_path):
    rng = np.random.default_rng(0)
    P = rng.uniform([0.6, -0.3, 0.3], [1.2, 0.3, 0.8], (60, 3))
    ds = Dataset(commanded=P, error=1e-4 * np.sin(P * 5) + rng.normal(0, 1e-5, (60, 3)), speed=np.full(60, 0.2))
    return HybridModel((), "tcp").fit(ds, thetas=[np.zeros(5)] * 3).save(tmp_path / "m")


def test_a_model_npz_with_an_extra_member_is_refused_before_reading_it(tmp_path):
    d = _model(tmp_path)
    with zipfile.ZipFile(d / "hybrid.npz", "a", compression=zipfile.ZIP_DEFLATED) as zf:
        # a zip bomb: 200 MB of zeros compress to about 200 kB
        zf.writestr("extra.npy", _npy(np.zeros(25_000_000)))
    with pytest.raises(DataError, match="unexpected member 'extra.npy'"):
        HybridModel.load(d)


def test_a_member_whose_header_claims_a_huge_array_is_refused(tmp_path):
    path = tmp_path / "x.npz"
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10 ** 9,)})
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("theta.npy", header.getvalue() + b"\0" * 64)  # the header writer adds the magic
    with pytest.raises(DataError, match="theta.npy.*exceed"):
        load_npz(path, ("theta",))


def test_an_object_array_is_refused(tmp_path):
    path = tmp_path / "o.npz"
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|O", "fortran_order": False, "shape": (1,)})
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("theta.npy", header.getvalue() + b"\0" * 8)
    with pytest.raises(DataError, match="not a plain number"):
        load_npz(path, ("theta",))


def test_a_saved_model_still_loads_and_predicts_the_same(tmp_path):
    d = _model(tmp_path)
    m = HybridModel.load(d)
    P = np.array([[0.9, 0.0, 0.5]])
    assert np.all(np.isfinite(m.predict(P)))


def test_a_nan_model_is_not_saved(tmp_path):
    d = _model(tmp_path)
    m = HybridModel.load(d)
    m.residual_rms_ = float("nan")
    with pytest.raises(DataError, match="NaN"):
        m.save(tmp_path / "nan")
    assert not (tmp_path / "nan" / "hybrid.json").exists()


def test_an_absurd_error_is_refused_with_its_row_and_the_json_stays_standard(tmp_path, capsys):
    rng = np.random.default_rng(1)
    n = 30
    P = rng.uniform([0.6, -0.3, 0.3], [1.2, 0.3, 0.8], (n, 3))
    E = rng.normal(0, 1e-4, (n, 3))
    E[7, 0] = 1e297  # 1e300 mm in the file
    csv = write_table(Dataset(commanded=P, error=E), tmp_path / "d.csv")
    rc = main(["fit", "--data", str(csv), "--out", str(tmp_path / "m"), "--json", "--no-progress"])
    out = capsys.readouterr().out

    def no_constants(c):
        raise ValueError(f"non-standard JSON constant {c}")

    res = json.loads(out, parse_constant=no_constants)
    assert rc == 2 and "data row 8" in res["error"] and "exceeds 1000 mm" in res["error"]
    assert not (tmp_path / "m").exists()


def test_plan_counts_are_bounded():
    from dt_kernel.config import validate

    base = {"registration_speed": 1.0}
    with pytest.raises(ConfigError, match="doe_reps"):
        validate(PlanConfig, base | {"doe_reps": 100_000_000}, "plan.yaml")
    with pytest.raises(ConfigError, match="doe_speeds"):
        validate(PlanConfig, base | {"doe_speeds": [0.5] * 1000}, "plan.yaml")
    assert validate(PlanConfig, base, "plan.yaml").doe_reps == 9


def _edit_gp(d, **changes):
    """Rewrite the saved GP's arrays with `changes` applied (name -> function of the array)."""
    with np.load(d / "gp.npz") as z:
        arrays = {k: z[k] for k in z.files}
    for k, f in changes.items():
        arrays[k] = f(arrays[k].copy())
    np.savez(d / "gp.npz", **arrays)


@pytest.mark.parametrize("changes,named", [
    ({"length_scales_0": lambda a: a * 0}, "length_scales .* must be positive and finite"),
    ({"x_scale_1": lambda a: -a}, "x_scale .* must be positive"),
    # a length scale near 0 through theta, the one predict reads, with length_scales edited to agree
    ({"theta_2": lambda a: np.r_[np.full(len(a) - 2, -60.0), a[-2:]],
      "length_scales_2": lambda a: a * 0 + 1e-30}, "must be at least 1e-06"),
    ({"length_scales_0": lambda a: a * 2}, "disagree with theta's"),
])
def test_a_twin_with_an_edited_gp_length_scale_is_refused_naming_it(tmp_path, changes, named):
    from dt_kernel.errors import ModelError

    d = _model(tmp_path)
    _edit_gp(d, **changes)
    with pytest.raises(ModelError, match=named) as exc:
        HybridModel.load(d)
    assert "GP model files are corrupt (output" in str(exc.value)
