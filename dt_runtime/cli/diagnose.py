"""`dt diagnose`: rank the physical effects the model lacks.

Grouped cross-validation (by target point) of the model with and without each candidate effect;
one-sided Wilcoxon test per held-out group.

`--auto`: the whole compare/diagnose/add loop in one command. Forward selection over the
candidate effects and the GP's inputs from the starting model: each step adds the change that
explains most held-out variance if it is significant at alpha / (candidates tested at that step)
and explains at least --min-explained; it stops at the first step where nothing qualifies. It
prints the steps (model, held-out 3D RMS with its uncertainty, p, explained fraction) and the
verdict: what was added and why, what is left, and how far the residual is from the noise floor.
"""
from __future__ import annotations

import argparse
from typing import Any

from dt_runtime.cli.common import (
    add_data_args,
    add_effects_file_arg,
    add_mpe_arg,
    add_output_args,
    folds,
    input_files,
    load,
    names,
    progress,
)


def add_arguments(dg: argparse.ArgumentParser) -> None:
    add_data_args(dg)
    dg.add_argument("--model", default=None, metavar="MODEL", help="starting model (default: --effects + GP)")
    dg.add_argument("--effects", default="", metavar="a,b,...", help="starting model's effects without --model")
    dg.add_argument("--candidates", default="", metavar="a,b,...", help="effects to test (default all)")
    add_effects_file_arg(dg)
    dg.add_argument("--folds", type=folds, default=5, help="cross-validation folds (default 5)")
    dg.add_argument("--auto", action="store_true", help="the whole loop: add effects / switch GP inputs while "
                    "significant (forward selection), then the verdict")
    dg.add_argument("--alpha", type=_fraction, default=0.01, help="--auto: family-wise level of each step (0.01)")
    dg.add_argument("--min-explained", type=_fraction, default=0.02,
                    help="--auto: smallest explained fraction of held-out variance worth adding (0.02)")
    dg.add_argument("--instruments", default=None, metavar="YAML",
                    help="the campaign's instruments and certificates (e.g. configs/instruments_example.yaml), "
                         "recorded in the provenance")
    add_mpe_arg(dg)
    add_output_args(dg)


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < v < 1:
        raise argparse.ArgumentTypeError(f"{v}: a fraction in (0, 1)")
    return v


def run(args: argparse.Namespace) -> Any:
    from dt_runtime.analysis.diagnose import diagnose, diagnose_auto
    from dt_runtime.cli.common import robot_of

    d = load(args)
    if args.auto:
        return diagnose_auto(d, args.model, names(args.effects), args.gp_inputs, robot_of(args, d),
                             names(args.candidates) or None, args.folds, args.seed, alpha=args.alpha,
                             min_explained=args.min_explained, progress=progress(args))

    return diagnose(d, args.model, names(args.effects), args.gp_inputs,
                        robot_of(args, d), names(args.candidates) or None, args.folds,
                        args.seed, progress=progress(args), instruments=args.instruments,
                        inputs=input_files(args))


def human(result: dict) -> str:
    if "steps" in result:  # --auto
        lines = [f"from {result['start']} ({result['n']} rows, {result['folds']}-fold CV grouped by point):"]
        for s in result["steps"]:
            lines.append(f"  {s['model']:<40} held-out {s['rmse_mm']:.4f} +/- {s['u_rmse_mm'] or 0:.4f} mm"
                         + (f"  -> {s['change']} (p = {s['p_value']:.2g}, explains "
                            f"{100 * s['explained_fraction']:.0f} %)" if s["change"] else ""))
        return "\n".join(lines + [result["verdict"]])
    lines = [f"held-out 3D RMS of the starting model: {result['rmse_base_mm']:.4f} mm"
             + (f" (noise floor {result['noise_floor_mm']:.4f} mm)" if result.get("noise_floor_mm") else "")]
    lines += [f"  {r['effect']:<10} explains {100 * r['explained_fraction']:6.1f} %  p = {r['p_value']:.2g}  "
              f"RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm" for r in result["ranking"]]
    lines += [f"  GP on {r['gp_inputs']:<9} explains {100 * r['explained_fraction']:6.1f} %  p = {r['p_value']:.2g}  "
              f"RMS {r['rmse_before_mm']:.4f} -> {r['rmse_after_mm']:.4f} mm"
              for r in result.get("gp_inputs_ranking", [])]
    return "\n".join(lines + [result["verdict"]])
