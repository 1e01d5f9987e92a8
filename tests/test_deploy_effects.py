"""Deployment of a map with physical effects, end to end through the command line: a campaign
on a cell whose arm expands with a warming, cycling shop temperature, written to files;
`dt calibrate` without and with the thermal effect; `dt run` of each twin on the same simulated
cell for the same program. The true 3D error of the commands falls when the effect is deployed
(the daemon reads the cell's temperature and the controller's joints before every command)."""
import json

from dt_runtime.cli.main import main
from dt_runtime.common.paths import CONFIGS


def _json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_the_thermal_effect_deployed_lowers_the_true_error(tmp_path, capsys):
    rc = main(["demo", "--config", str(CONFIGS / "demo_thermal.yaml"), "--quick", "--out", str(tmp_path / "demo"),
               "--json", "--no-progress"])
    assert rc == 0, capsys.readouterr()
    capsys.readouterr()
    true_rms = {}
    for name, effects in (("gpr", ""), ("geometric", "geometric"), ("thermal", "geometric,thermal")):
        rc = main(["calibrate", "--campaign", str(tmp_path / "demo" / "campaign"), "--effects", effects,
                   "--out", str(tmp_path / name), "--json", "--no-progress"])
        s = _json(capsys)
        assert rc == 0, s
        if name == "thermal":  # the expansion coefficient found is the simulated arm's (2.3e-5 /K)
            alpha = next(p for p in s["maps"]["e_lt"]["parameters"] if p["name"] == "alpha")
            assert abs(alpha["value"] - 2.3e-5) < 0.1 * 2.3e-5, alpha
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
