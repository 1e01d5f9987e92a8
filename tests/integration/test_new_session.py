"""A model deployed to a new session (another day, the tracker set up anew): `dt compare` registers
the session on 10 reference poses with the model's correction applied and tests every other row
after that registration; its `validity` says whether the stated U95 covers them. On the project's
multi-session campaign generator (a UR10 with its own geometric errors, the tracker's frame
different each session)."""
import json

import pytest

from dt_runtime.cli.main import main
from tests.support.campaign_generator import write_campaign


@pytest.fixture(scope="module")
def deployed(tmp_path_factory):
    d = tmp_path_factory.mktemp("new_session")
    truth = write_campaign(d, seed=7, n_points=40, passes=2, sessions=4)
    files = [str(f) for f in truth["files"]]
    assert main(["fit", "--data", files[0], files[1], "--mapping", str(truth["mapping"]), "--effects", "geometric",
                 "--out", str(d / "model"), "--no-progress"]) == 0
    return d, files, str(truth["mapping"])


def _compare(capsys, d, data, mapping, *extra):
    capsys.readouterr()
    rc = main(["compare", "--data", data, "--mapping", mapping, "--model", str(d / "model"), "--json",
               "--no-progress", *extra])
    return rc, json.loads(capsys.readouterr().out)


def test_after_registration_on_reference_poses_the_new_session_passes_eq17_and_u95_covers(deployed, capsys):
    d, files, mapping = deployed
    rc, r = _compare(capsys, d, files[2], mapping)
    assert rc == 0
    ar = r["models"][-1]["after_registration"]
    assert ar["reference_poses"] == 10 and ar["n"] == 60  # 80 rows, 10 poses x 2 passes used by the registration
    before, after = ar["before"], ar
    assert max(before["failures_per_axis"].values()) > 0.2  # under the data's own registration: false alarms
    assert max(after["failures_per_axis"].values()) <= 0.1
    assert all(0.9 <= c <= 1.0 for c in after["coverage_95"].values())
    assert after["rmse_mm"] < before["rmse_mm"]
    s = ar["sessions"][0]
    assert s["registration_dof"] == 3 * 20 - 6 and all(u > 0 for u in s["u_registration_mm"].values())
    assert r["validity"]["status"] == "ok"
    assert "rows of the new session(s) not used by the registration" in r["validity"]["checks"][0]["what"]


def test_without_the_registration_the_validity_says_the_u95_does_not_cover(deployed, capsys):
    d, files, mapping = deployed
    rc, r = _compare(capsys, d, files[2], mapping, "--reference", "0", "--strict")
    assert "after_registration" not in r["models"][-1]
    assert r["validity"]["status"] == "fail" and rc == 3
    assert "too small" in r["validity"]["checks"][0]["finding"]


def test_the_human_output_ends_with_the_validity_line_and_shows_before_and_after(deployed, capsys):
    d, files, mapping = deployed
    capsys.readouterr()
    assert main(["compare", "--data", files[2], "--mapping", mapping, "--model", str(d / "model"),
                 "--no-progress"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1].startswith("validity: OK")
    assert any("registered on 10 reference poses" in ln and "->" in ln for ln in out)


def test_a_training_session_is_in_sample_and_its_validity_unchecked(deployed, capsys):
    d, files, mapping = deployed
    rc, r = _compare(capsys, d, files[0], mapping)
    assert r["validity"]["status"] == "unchecked" and "in-sample" in r["validity"]["finding"]


@pytest.fixture(scope="module")
def drift_model():
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.models.hybrid import HybridModel
    from tests.support.ur10_generator import generate

    train = generate("drift", 3, n_points=40, passes=3)  # the joints drift during this session
    m = HybridModel(("geometric", "drift"), "none", robot=CONFIGS / "robots" / "ur10.yaml").fit(train)
    assert m.time_effects() == ("drift",)
    return train, m


def test_a_drift_found_in_one_session_is_not_carried_into_another_without_a_clock(drift_model):
    from dataclasses import replace

    import numpy as np

    from dt_runtime.analysis.compare import compare
    from tests.support.ur10_generator import generate

    _, m = drift_model
    new = generate("none", 53, n_points=30, passes=1, arm_seed=3)  # another day: its own t from 0
    r, arrays = compare([m], new, reference=10)
    block = r.to_dict()["models"][-1]
    note = block["time_terms"]
    assert note["applied"].startswith("not applied") and "no absolute time" in note["text"]
    # the prediction is the map without its drift there, not the drift evaluated at the file's own clock
    D = m.design_matrix(replace(new, t=np.zeros(new.n)))
    keep = np.array([e != "drift" for e, _, _, _ in D.params])
    expected = np.einsum("nap,p->na", D.A[:, :, keep], m.theta_[keep])
    assert arrays["models"][-1]["predicted"] == pytest.approx(expected, abs=1e-12)
    ar = block["after_registration"]
    assert all(0.9 <= c <= 1.0 for c in ar["coverage_95"].values()) and r.validity["status"] == "ok"


def test_with_unix_time_in_both_files_the_drift_is_carried_and_extrapolation_is_counted(drift_model):
    from dataclasses import replace

    from dt_runtime.analysis.compare import compare
    from dt_runtime.common.paths import CONFIGS
    from dt_runtime.models.hybrid import HybridModel
    from tests.support.ur10_generator import generate

    train, _ = drift_model
    epoch = 1.7e9  # 2023-11-14
    m = HybridModel(("geometric", "drift"), "none", robot=CONFIGS / "robots" / "ur10.yaml").fit(
        replace(train, t=train.t + epoch))
    new = generate("none", 53, n_points=30, passes=1, arm_seed=3)
    later = replace(new, t=new.t + epoch + train.t.max() + 3600.0)  # an hour after the training ended
    r, _ = compare([m], later, reference=10)
    note = r.to_dict()["models"][-1]["time_terms"]
    assert note["applied"] == "absolute time" and note["rows_beyond_training"] == 30
    assert note["hours_beyond_training"] == pytest.approx((new.t.max() + 3600.0) / 3600.0)
