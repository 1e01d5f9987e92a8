"""Deployment of a map with physical effects, end to end through the command line: a campaign
on a cell whose arm expands with a warming, cycling shop temperature, written to files;
`dt calibrate` without and with the thermal effect (the validation phase flags the twins that miss
it, and passes the one that has it); `dt run` of each twin on the same simulated cell for the same
program. The true 3D error of the commands falls when the effect is deployed
(the daemon reads the cell's temperature and the controller's joints before every command)."""
import json

from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS


def _json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_the_thermal_effect_deployed_lowers_the_true_error(tmp_path, capsys):
    # The demo's GPR twin misses the expansion: its stated U covers a fraction of the true errors,
    # which the summary, the report's first screen and the last line say; --strict exits 3.
    rc = main(["demo", "--config", str(CONFIGS / "demo_thermal.yaml"), "--quick", "--out", str(tmp_path / "demo"),
               "--json", "--no-progress", "--strict"])
    s = _json(capsys)
    assert rc == 3, s
    check = s["validity"]["checks"][0]
    assert s["validity"]["status"] == "fail" and check["check"] == "coverage_validation"
    # the held-out conformal factor widens U (x about 1.5 here) but the validation's temperature is not the
    # DOE's: new positions are not exchangeable with the held-out ones, and U still fails to cover
    assert s["uncertainty_calibration"]["factor"][0] > 1.2
    assert check["axes"]["x"]["coverage"] < 0.7 and check["axes"]["x"]["status"] == "fail"
    assert check["cause"] == "the model misses a time-dependent effect" and "temperature changed" in check["evidence"]
    assert s["validity"]["checks"][1]["check"] == "eq17_vs_coverage" and s["validity"]["checks"][1]["status"] == "fail"
    first_screen = (tmp_path / "demo" / "report.html").read_text(encoding="utf-8").split("<img", 1)[0]
    assert "NOT VALID" in first_screen and "the model misses a time-dependent effect" in first_screen
    true_rms = {}
    for name, effects in (("gpr", ""), ("geometric", "geometric"), ("thermal", "geometric,thermal")):
        rc = main(["calibrate", "--campaign", str(tmp_path / "demo" / "campaign"), "--effects", effects,
                   "--out", str(tmp_path / name), "--json", "--no-progress", "--strict"])
        s = _json(capsys)
        # the campaign's validation phase (uncorrected, tracker-measured) checks each twin's U
        assert s["validation"]["n"] == 28
        if name == "thermal":  # the expansion coefficient found is the simulated arm's (2.3e-5 /K)
            assert rc == 0 and s["validity"]["status"] == "ok", s["validity"]["line"]
            alpha = next(p for p in s["maps"]["e_lt"]["parameters"] if p["name"] == "alpha")
            assert abs(alpha["value"] - 2.3e-5) < 0.1 * 2.3e-5, alpha
            report = (tmp_path / name / "report.html").read_text(encoding="utf-8")
            assert "geometric + thermal + GP" in report and "alpha 22.9" in report and "Not shown" not in report
        else:  # the expansion missed: the tracker's errors at the validation points leave the stated U
            # (the held-out conformal factor widens U by what the DOE's own held-out errors show, so over
            # these 28 positionings the miss may be established (fail) or only below the band (warn))
            st = s["validity"]["status"]
            assert st in ("warn", "fail") and rc == (3 if st == "fail" else 0), s["validity"]["line"]
            assert min(s["validity"]["checks"][0]["axes"][ax]["coverage"] for ax in "xyz") < 0.9
            assert "--effects geometric,thermal" in s["validity"]["checks"][0]["advice"]
        cfg = tmp_path / f"run_{name}.yaml"
        cfg.write_text(f"""
twin: {tmp_path / name}
store: {tmp_path / name / 'run.sqlite'}
realtime: false
publish: false
drivers: {{robot: sim, tracker: sim, camera: sim_point}}
sim: {{scenario: {CONFIGS / 'scenarios/hidden/thermal.yaml'}, cell: {CONFIGS / 'cell.yaml'}}}
path: {{kind: program, program: {CONFIGS / 'programs/validation_points.csv'}}}
""")
        rc = main(["run", "--config", str(cfg), "--duration", "3600", "--json"])  # an hour: 20 -> 24 C +/- 3 C
        r = _json(capsys)
        assert rc == 0 and r["refused_commands"] == 0 and r["ticks"] > 300, r
        true_rms[name] = r["true_rms_mm"]
    # measured (seed 1): 0.049 mm (GPR), 0.048 mm (geometric + GP), 0.008 mm (+ thermal)
    assert true_rms["thermal"] < 0.5 * min(true_rms["gpr"], true_rms["geometric"]), true_rms
