"""May the stated figures be trusted? The `validity` block of a summary (`dt demo`, `dt calibrate`):
each check of a stated uncertainty against what was really found (the coverage of U(TCP_c), and
Eq. 17 against that coverage), its band, its status and, when it fails, the likely cause and what
to do next, in words; the command line prints its `line` last.

The checks, the status rules and the block's keys: docs/cli.md, "Validity: every figure carries
its own".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dt_kernel.units import AXES, MM_PER_M
from dt_runtime.metrology.stats import wilson_interval
from dt_runtime.models.effects import Inputs

BAND = (0.90, 0.99)  # the coverage a 95 % expanded uncertainty should reach over a finite set of targets
RANK = {"ok": 0, "warn": 1, "fail": 2}
SYMBOL = {"ok": "OK", "warn": "WARNING", "fail": "NOT VALID", "unchecked": "NOT CHECKED"}
BIAS_SHARE = 0.5  # mean^2 / (mean^2 + variance) above which the misses share a common offset
UNSEEN_SHARE = 0.1  # share of positions in a joint configuration the DOE lacks that can explain misses
DELTA_T_C = 0.5  # deg C: a temperature this far beyond the DOE's range is a changed condition
GENERIC_CAUSE = "an effect the model does not learn from the position and speed (e.g. the direction of approach)"


def configuration(q: np.ndarray) -> np.ndarray:
    """The joint configuration of each row: the sign of the elbow (q3: up/down) and the wrist (q5:
    flip) joints, as 'q3+,q5-' (empty for an arm with fewer joints).

    Parameters
    ----------
    q : ndarray
        (n, dof) joint angles, rad.

    Returns
    -------
    ndarray
        (n,) labels.
    """
    cols = [j for j in (2, 4) if j < q.shape[1]]
    return np.array([",".join(f"q{j + 1}{'+' if row[j] >= 0 else '-'}" for j in cols) for row in q], dtype=object)


@dataclass(frozen=True)
class Sample:
    """Positions whose error their stated U(TCP_c) should cover."""

    key: str  # "inside", "outside", "validation"
    what: str  # the positions in words: "the 28 corrected validation positionings"
    truth: str  # the errors in words: "true errors (simulator)", "errors the laser tracker measured"
    error: np.ndarray  # (n,3) m
    U: np.ndarray  # (n,3) m, the stated expanded uncertainty of each position
    conditions: Inputs  # the commanded targets (distinct ones counted) and, where known, joints, time, temperature
    requested: int | None = None  # the number of targets asked for, when fewer were reached
    outside_hull: bool = False  # the positions lie beyond the calibrated volume (extrapolation)
    stated: str = "U(TCP_c)"  # the stated uncertainty in words
    outside_domain: str | None = None  # most positions lie beyond the model's training data: in words


@dataclass(frozen=True)
class Eq17Rates:
    """The Eq. 17 t-test on the same positionings as a coverage sample."""

    passed: np.ndarray  # (n,3) bool
    U_diff: np.ndarray  # (3,) m, U(e_LT_hat - e_MVS) of Eq. 20: the test's own uncertainty (with Eq. 22's)


def distinct(points: np.ndarray, tol: float = 1e-6) -> int:
    """The number of distinct points (to `tol`).

    Parameters
    ----------
    points : ndarray
        (n, 3) m.
    tol : float
        Points that round to the same multiple of `tol` (m; default 1 um) are one.

    Returns
    -------
    int
    """
    if len(points) == 0:
        return 0
    return len(np.unique(np.round(np.asarray(points, float) / tol).astype(np.int64), axis=0))


def axis_status(p: float, n_eff: int) -> tuple[str, tuple[float, float]]:
    """The status of a coverage fraction `p` over `n_eff` independent targets, and its interval.

    Parameters
    ----------
    p : float
        The fraction covered, 0-1.
    n_eff : int
        The number of independent targets (distinct ones).

    Returns
    -------
    status : str
        'fail' (the interval wholly below `BAND`), 'warn' (the fraction below the band, or the
        interval wholly above it) or 'ok'.
    interval : tuple of float
        The 95 % Wilson interval of the fraction.
    """
    lo, hi = wilson_interval(p * n_eff, n_eff)
    if hi < BAND[0]:
        return "fail", (lo, hi)
    if p < BAND[0] or lo > BAND[1]:
        return "warn", (lo, hi)
    return "ok", (lo, hi)


def _pct(p: float) -> str:
    return f"{100 * p:.1f} %"


def _worst(statuses) -> str:
    return max(statuses, key=lambda s: RANK[s], default="ok")


def coverage_check(s: Sample, ref: Inputs | None, campaign: str | None) -> dict:
    """The coverage check of one sample: per axis fraction, interval and status, and the words.

    Parameters
    ----------
    s : Sample
        The positions, their errors and stated U (m).
    ref : Inputs or None
        The DOE's conditions, to name a likely cause of a low coverage.
    campaign : str or None
        The campaign's manifest, for the advice.

    Returns
    -------
    dict
        One entry of the block's `checks` (keys in docs/cli.md, "Validity").
    """
    inside = np.abs(s.error) <= s.U
    n = len(inside)
    n_eff = min(n, distinct(s.conditions.commanded))
    axes: dict[str, dict[str, Any]] = {}
    for k, ax in enumerate(AXES):
        p = float(inside[:, k].mean())
        st, (lo, hi) = axis_status(p, n_eff)
        axes[ax] = {"coverage": p, "inside": int(inside[:, k].sum()), "n": n, "interval_95": [lo, hi], "status": st}
    status = _worst(a["status"] for a in axes.values())
    low = [ax for ax, a in axes.items() if a["coverage"] < BAND[0]]
    high = [ax for ax, a in axes.items() if a["status"] == "warn" and a["coverage"] > BAND[1]]
    where = f"the {s.truth} at {s.what}"
    shown = low or high or list(AXES)

    def figs(axs, counts: bool = True) -> str:
        return ", ".join(f"{ax} {_pct(axes[ax]['coverage'])}" + (f" ({axes[ax]['inside']} of {n})" if counts else "")
                         for ax in axs)

    tell = (f"; 95 % interval over {n_eff} distinct targets: "
            + ", ".join(f"{ax} {100 * axes[ax]['interval_95'][0]:.1f}-{100 * axes[ax]['interval_95'][1]:.1f} %"
                        for ax in shown))
    band = f"the band {100 * BAND[0]:.0f}-{100 * BAND[1]:.0f} %"
    if status == "fail":
        finding = f"the stated {s.stated} is too small: it covers {figs(low)} of {where}, below {band}{tell}"
    elif low:
        finding = (f"the stated {s.stated} may be too small: it covers {figs(low)} of {where}, below {band}, though "
                   f"{n_eff} targets cannot establish it{tell}")
    elif high:
        finding = (f"the stated {s.stated} is larger than the errors need: it covers {figs(high)} of {where}, above "
                   f"{band}{tell}")
    else:
        finding = f"the stated {s.stated} covers {figs(AXES)} of {where}, within {band}"
        over = [ax for ax, a in axes.items() if a["coverage"] > BAND[1]]
        if over:
            finding += (f" ({', '.join(over)} above it, but within what {n_eff} targets can tell: the 95 % interval "
                        "reaches the band)")
    short = f"{s.stated} covers {figs(shown, counts=False)} of {where} (band {100 * BAND[0]:.0f}-{100 * BAND[1]:.0f} %)"
    out: dict[str, Any] = {"check": f"coverage_{s.key}", "what": f"coverage of {s.stated} at {s.what}",
                           "stated": s.stated, "truth": s.truth, "band": list(BAND), "n": n, "n_distinct": n_eff,
                           "axes": axes, "status": status, "finding": finding, "short": short}
    if s.requested is not None and n < s.requested:
        out["n_requested"] = s.requested
        out["finding"] += (f" ({n} of the {s.requested} positions asked for were reached: the arm could not reach "
                           "the others from where it stood)")
    if low:
        out["cause"], out["evidence"], out["advice"] = _cause_low(s, ref, low, inside, campaign)
        if status == "warn" and out["cause"] == GENERIC_CAUSE:  # not established, and the data point nowhere
            out["cause"] = f"none found in the data: possibly chance with {n_eff} targets"
            out["evidence"] = ("no position in a joint configuration the DOE lacks, no offset shared by the misses "
                               "after the temperature or the time moved on")
            out["advice"] = "validate on more targets before trusting or doubting this U"
    elif high:
        out["cause"] = "the budget states more than the errors need"
        out["evidence"] = ("a conservative type B component (e.g. the laser tracker's traceability, which the "
                           "simulator's truth does not need) or a double count")
        out["advice"] = "read the budget's shares (report: Uncertainty) before relying on a smaller U"
    return out


def _cause_low(s: Sample, ref: Inputs | None, low: list[str], inside: np.ndarray,
               campaign: str | None) -> tuple[str, str, str]:
    """The likely cause of a coverage below the band, from the data: a joint configuration the DOE
    never measured, a condition (temperature, time) that changed since the DOE with the misses
    sharing an offset, extrapolation, or else an error the model cannot learn."""
    cond = s.conditions
    ks = [AXES.index(ax) for ax in low]
    again = f"dt calibrate --campaign {campaign}" if campaign else "dt calibrate (the same files)"
    if cond.joints is not None and ref is not None and ref.joints is not None:
        lab = configuration(cond.joints)
        known = set(configuration(ref.joints))
        unseen = np.array([x not in known for x in lab])
        if unseen.mean() >= UNSEEN_SHARE and np.any(unseen) and not np.all(unseen):
            seen_cov = inside[~unseen][:, ks].mean(axis=0)
            unseen_cov = inside[unseen][:, ks].mean(axis=0)
            if np.all(unseen_cov < seen_cov):
                names = ", ".join(f"({x})" for x in sorted(set(lab[unseen])))
                return ("a joint configuration the DOE never measured: the error map of one configuration does not "
                        "hold in another",
                        f"{int(unseen.sum())} of {len(lab)} positions were reached in {names} (the DOE's: "
                        f"{', '.join(f'({x})' for x in sorted(known))}); there U covers "
                        + ", ".join(f"{ax} {_pct(c)}" for ax, c in zip(low, unseen_cov)) + ", elsewhere "
                        + ", ".join(f"{ax} {_pct(c)}" for ax, c in zip(low, seen_cov)),
                        "keep the arm in the DOE's joint configurations, or measure a DOE in the other one too")
    if s.outside_domain:
        return ("extrapolation beyond the model's training data", s.outside_domain,
                "train on data that cover these positions and joint ranges, or keep the cell inside the trained "
                "domain")
    e = s.error[:, ks]
    mean, sd = e.mean(axis=0), e.std(axis=0)
    share = mean ** 2 / np.maximum(mean ** 2 + sd ** 2, 1e-30)
    changed = _changed_conditions(cond, ref)
    if changed and np.any(share > BIAS_SHARE):
        offset = ", ".join(f"{ax} {mean[i] * MM_PER_M:+.3f} mm" for i, ax in enumerate(low) if share[i] > BIAS_SHARE)
        spread = max(float(sd[i]) for i in range(len(low)) if share[i] > BIAS_SHARE) * MM_PER_M
        effect = "thermal" if "temperature" in changed else "drift"
        return ("the model misses a time-dependent effect",
                f"the errors share an offset ({offset}, against a spread of {spread:.3f} mm) and {changed}",
                f"try dt diagnose (it names the missing effect), or calibrate with it: {again} "
                f"--effects geometric,{effect} --out TWIN")
    if s.outside_hull:
        return ("extrapolation beyond the calibrated volume",
                "there the error grows faster than U's extrapolation term kappa d(c) states",
                "keep commands inside the calibrated volume (dt correct --refuse-outside) or extend the DOE")
    return (GENERIC_CAUSE,
            "the model's error at new targets is larger than its held-out spread over the DOE, to which U is scaled",
            "try dt diagnose to name the missing effect, then calibrate with it (dt calibrate --effects ...)")


def _changed_conditions(cond: Inputs, ref: Inputs | None) -> str:
    """What changed between the DOE and these positions, in words ('' if nothing known did)."""
    if ref is None:
        return ""
    out = []
    if cond.temperature is not None and ref.temperature is not None:
        tc, tr = cond.temperature[np.isfinite(cond.temperature)], ref.temperature[np.isfinite(ref.temperature)]
        if len(tc) and len(tr) and (tc.max() > tr.max() + DELTA_T_C or tc.min() < tr.min() - DELTA_T_C
                                    or abs(tc.mean() - tr.mean()) > DELTA_T_C):
            out.append(f"the temperature changed: {tc.min():.1f}-{tc.max():.1f} °C here, {tr.min():.1f}-"
                       f"{tr.max():.1f} °C during the DOE")
    if cond.t is not None and ref.t is not None:
        tc, tr = cond.t[np.isfinite(cond.t)], ref.t[np.isfinite(ref.t)]
        if len(tc) and len(tr) and tc.min() >= tr.max():
            out.append(f"these positions were measured {_duration(tc.min() - tr.max())} to "
                       f"{_duration(tc.max() - tr.max())} after the DOE ended")
    return "; ".join(out)


def _duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 3600 else f"{s / 60:.0f} min" if s >= 60 else f"{s:.0f} s"


def eq17_check(s: Sample, cov: dict, rates: Eq17Rates) -> dict:
    """Eq. 17 on the positionings of coverage sample `s` against its coverage check `cov`: does
    the in-service t-test say what the truth says?

    Parameters
    ----------
    s : Sample
        The coverage sample whose positionings were tested.
    cov : dict
        Its coverage check (`coverage_check`).
    rates : Eq17Rates
        Eq. 17's outcomes at the same positionings.

    Returns
    -------
    dict
        The `eq17_vs_coverage` check: 'fail' on an axis where Eq. 17 and the coverage disagree.
    """
    n = len(rates.passed)
    n_eff = min(n, cov["n_distinct"])
    axes: dict[str, dict[str, Any]] = {}
    worse: list[str] = []
    alarms: list[str] = []
    for k, ax in enumerate(AXES):
        p = float(rates.passed[:, k].mean()) if n else float("nan")
        st, (lo, hi) = axis_status(p, n_eff) if n else ("ok", (float("nan"), float("nan")))
        c = cov["axes"][ax]
        disagree = (c["status"] == "fail" and p >= BAND[0]) or (st == "fail" and c["coverage"] >= BAND[0])
        if disagree and c["status"] == "fail":
            worse.append(ax)
        elif disagree:
            alarms.append(ax)
        axes[ax] = {"pass_fraction": p, "coverage": c["coverage"], "interval_95": [lo, hi],
                    "status": "fail" if disagree else "ok"}
    status = "fail" if worse or alarms else "ok"
    out: dict[str, Any] = {"check": "eq17_vs_coverage",
                           "what": f"the Eq. 17 t-test against the coverage of U(TCP_c) at {s.what}",
                           "band": list(BAND), "n": n, "axes": axes, "status": status}
    if worse:
        rms = np.sqrt(np.mean(s.error ** 2, axis=0)) * MM_PER_M
        out["finding"] = ("Eq. 17 passes " + ", ".join(f"{ax} {_pct(axes[ax]['pass_fraction'])}" for ax in worse)
                          + " of these positionings while U(TCP_c) covers "
                          + ", ".join(f"{ax} {_pct(axes[ax]['coverage'])}" for ax in worse)
                          + " of their errors: in service the t-test would not notice this error")
        out["short"] = ("Eq. 17 passes " + ", ".join(f"{ax} {_pct(axes[ax]['pass_fraction'])}" for ax in worse)
                        + " there: the in-service t-test would not notice")
        out["cause"] = "Eq. 17's uncertainty is wider than the error the correction leaves"
        out["evidence"] = ("Eq. 17 weighs e_LT_hat - e_MVS against e_MVS-LT_hat within U(e_LT_hat - e_MVS) (Eq. 20: "
                           + ", ".join(f"{ax} {rates.U_diff[AXES.index(ax)] * MM_PER_M:.3f} mm" for ax in worse)
                           + "); the corrected error: "
                           + ", ".join(f"{ax} {rms[AXES.index(ax)]:.3f} mm RMS" for ax in worse))
        out["advice"] = "trust the coverage, not Eq. 17, here: fix the model first (see the coverage check)"
    elif alarms:
        out["finding"] = ("Eq. 17 fails " + ", ".join(f"{ax} {_pct(1 - axes[ax]['pass_fraction'])}" for ax in alarms)
                          + " of these positionings although U(TCP_c) covers their errors: in service it would "
                          "raise false maintenance requests")
        out["short"] = ("Eq. 17 fails " + ", ".join(f"{ax} {_pct(1 - axes[ax]['pass_fraction'])}" for ax in alarms)
                        + " where U(TCP_c) covers the errors: false alarms in service")
        out["cause"] = "the camera's registration or its e_MVS-LT map is off"
        out["evidence"] = "the camera disagrees with the tracker-trained twin where the twin is right"
        out["advice"] = "check the camera system's registration and calibration, then calibrate again"
    else:
        out["finding"] = out["short"] = ("Eq. 17 and the coverage agree: "
                          + ", ".join(f"{ax} passes {_pct(axes[ax]['pass_fraction'])}, covers "
                                      f"{_pct(axes[ax]['coverage'])}" for ax in AXES))
    return out


def assess(samples: list[Sample], ref: Inputs | None = None, eq17: tuple[str, Eq17Rates] | None = None,
           campaign: str | None = None, unchecked: str | None = None) -> dict:
    """The validity block: every coverage sample checked, Eq. 17 against the sample it names
    (`(sample key, rates)`), the status and one line. `ref`: the DOE's conditions (for the
    causes); `campaign`: the campaign's manifest, for the advice; `unchecked`: why nothing could
    be checked, when there is no sample.

    Parameters
    ----------
    samples : list of Sample
        The coverage samples; empty ones are skipped.
    ref : Inputs or None
        The DOE's conditions.
    eq17 : tuple of (str, Eq17Rates) or None
        The key of the sample Eq. 17 was run on, and its outcomes.
    campaign : str or None
        The campaign's manifest.
    unchecked : str or None
        Why nothing could be checked (the finding when no check is made).

    Returns
    -------
    dict
        The block: `status` ('ok', 'warn', 'fail' or 'unchecked'), `band`, `checks`, `line`.
    """
    checks = []
    by_key = {}
    for s in samples:
        if len(s.error) == 0:
            continue
        c = coverage_check(s, ref, campaign)
        checks.append(c)
        by_key[s.key] = (s, c)
    if eq17 is not None and eq17[0] in by_key and len(eq17[1].passed):
        checks.append(eq17_check(*by_key[eq17[0]], eq17[1]))
    if not checks:
        why = unchecked or "no coverage check was made"
        return {"status": "unchecked", "band": list(BAND), "checks": [], "finding": why,
                "line": f"validity: {SYMBOL['unchecked']}: {why}"}
    status = _worst(c["status"] for c in checks)
    return {"status": status, "band": list(BAND), "checks": checks, "line": line(status, checks)}


def _over_covered(checks: list[dict]) -> str:
    """Words for an OK whose coverage lies above the band (100.0 % against 90-99 %): too few targets
    to tell it from 95 %, and if it holds, U is conservative (larger than the errors need)."""
    over = [(c, ax, a) for c in checks if c.get("check", "").startswith("coverage_")
            for ax, a in (c.get("axes") or {}).items() if a.get("coverage", 0) > BAND[1]]
    if not over:
        return ""
    c = over[0][0]
    axes = ", ".join(f"{ax} {_pct(a['coverage'])}" for cc, ax, a in over if cc is c)
    return (f"; {axes} lies above the band, which {c.get('n_distinct', c.get('n'))} distinct targets cannot tell "
            f"from 95 % (the 95 % interval reaches the band); if it holds, the stated {c.get('stated', 'U')} is "
            "conservative: larger than the errors need")


def line(status: str, checks: list[dict]) -> str:
    """The command's last line: the worst check in short, its likely cause and what to do next
    (the evidence is in the check's `finding` and `evidence`).

    Parameters
    ----------
    status : str
        The block's status ('ok', 'warn' or 'fail').
    checks : list of dict
        The checks (`coverage_check`, `eq17_check`), at least one with that status unless 'ok'.

    Returns
    -------
    str
    """
    if status == "ok":
        stated = checks[0].get("stated", "U(TCP_c)")
        text = (f"validity: {SYMBOL['ok']}: the stated {stated} covers the errors within the band "
                f"{100 * BAND[0]:.0f}-{100 * BAND[1]:.0f} % in every check ({len(checks)})")
        return text + _over_covered(checks)
    first = next(c for c in checks if c["status"] == status)
    text = f"validity: {SYMBOL[status]}: {first['short']}"
    eq17 = next((c for c in checks if c["check"] == "eq17_vs_coverage" and c is not first and c["status"] != "ok"),
                None)
    if eq17 is not None:
        text += f"; {eq17['short']}"
    if first.get("cause"):
        text += f"; likely cause: {first['cause']}"
    if first.get("advice"):
        text += f"; next: {first['advice']}"
    others = [c for c in checks if c is not first and c is not eq17 and c["status"] != "ok"]
    if others:
        text += f" (and {len(others)} more check{'s' if len(others) > 1 else ''} flagged: the summary's validity)"
    return text


def restated(block: dict) -> str | None:
    """A stored validity block's line as this version words it (a summary written before the words
    for a coverage above the band said only "OK"), else the line stored.

    Parameters
    ----------
    block : dict
        A summary's `validity` (status, checks, line).

    Returns
    -------
    str or None
    """
    status, checks = block.get("status"), block.get("checks")
    if status in RANK and isinstance(checks, list) and checks and all(isinstance(c, dict) for c in checks):
        try:
            return line(status, checks)
        except (KeyError, TypeError, ValueError, StopIteration, AttributeError):
            pass
    return block.get("line")
