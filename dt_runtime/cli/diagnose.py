"""`dt diagnose`: rank the physical effects the model lacks.

Grouped cross-validation (by target point) of the model with and without each candidate effect;
one-sided Wilcoxon test per held-out group.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import add_data_args, add_output_args, folds, load, names, progress


def add_arguments(dg: argparse.ArgumentParser) -> None:
    add_data_args(dg)
    dg.add_argument("--model", default=None, metavar="MODEL", help="starting model (default: --effects + GP)")
    dg.add_argument("--effects", default="", metavar="a,b,...", help="starting model's effects without --model")
    dg.add_argument("--candidates", default="", metavar="a,b,...", help="effects to test (default all)")
    dg.add_argument("--folds", type=folds, default=5, help="cross-validation folds (default 5)")
    dg.add_argument("--instruments", default=None, metavar="YAML",
                    help="the campaign's instruments and certificates (e.g. configs/instruments_example.yaml), "
                         "recorded in the provenance")
    add_output_args(dg)


def run(args: argparse.Namespace) -> Any:
    from dt_runtime.analysis.data import DEFAULT_ROBOT
    from dt_runtime.analysis.diagnose import diagnose

    return diagnose(load(args), args.model, names(args.effects), args.gp_inputs,
                        args.robot or DEFAULT_ROBOT, names(args.candidates) or None, args.folds,
                        args.seed, progress=progress(args), instruments=args.instruments,
                        inputs=[args.mapping] if args.mapping else [])


def human(result: dict) -> str:
    lines = [f"held-out 3D RMS of the starting model: {result['rmse_base_mm']:.4f} mm"
             + (f" (noise floor {result['noise_floor_mm']:.4f} mm)" if result.get("noise_floor_mm") else "")]
    lines += [f"  {r['effect']:<10} explains {100 * r['explained_fraction']:6.1f} %  p = {r['p_value']:.2g}  "
              f"RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm" for r in result["ranking"]]
    lines += [f"  GP on {r['gp_inputs']:<9} explains {100 * r['explained_fraction']:6.1f} %  p = {r['p_value']:.2g}  "
              f"RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm"
              for r in result.get("gp_inputs_ranking", [])]
    return "\n".join(lines + [result["verdict"]])
