"""Retake the screenshots of the reports' first screens in docs/screenshots/ with a headless browser.

    .venv/bin/python docs/tools/screenshots.py [--work DIR] [--browser chromium]

Runs, with this checkout's `dt` (about 3 minutes of CPU on 2 cores):
- the thermal quick demo, `dt demo --config configs/demo_thermal.yaml --quick` (its GPR twin misses
  the arm's expansion: the report opens with NOT VALID and the likely cause) -> demo.png;
- `dt calibrate` of that campaign with `--effects geometric,thermal` (validated on the campaign's
  validation phase against the tracker: OK; the fitted expansion coefficient) -> calibrate.png;
- the README's backlash loop (`dt simulate` of configs/scenarios/hidden/backlash.yaml, three `dt fit`
  models, `dt compare --cv 5 --report`) -> compare.png;
and photographs each report.html with `chromium --headless --no-sandbox --disable-gpu
--screenshot=... --window-size=...` (the Debian package `chromium`; no driver library, nothing
downloaded). Each PNG is reduced to a 256-colour palette (Pillow, matplotlib's dependency) to stay
well under 300 kB. The work directory (default out/screenshots, relative to the checkout, so the
reports show short paths) keeps the outputs.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "screenshots"
WINDOW = (1280, 1100)  # px: the first screen of a laptop, the whole validity box and the key figures
MAX_BYTES = 300_000


def dt(*args: str) -> None:
    """Run `dt` (this interpreter's) from the checkout's root; its output goes to ours. A validity
    check that fails is what the demo shows: only a usage or input error (exit 2) or a defect (1) stops."""
    rc = subprocess.run([sys.executable, "-m", "dt_runtime.cli", *args, "--no-progress"], cwd=ROOT).returncode
    if rc not in (0, 3):
        raise SystemExit(f"dt {' '.join(args)}: exit {rc}")


def shoot(browser: str, html: Path, png: Path) -> None:
    """The first screen of `html` as a palette PNG."""
    from PIL import Image

    raw = png.with_suffix(".raw.png")
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={raw}", f"--window-size={WINDOW[0]},{WINDOW[1]}", html.resolve().as_uri()],
                   check=True, capture_output=True)
    Image.open(raw).convert("RGB").quantize(colors=256).save(png, optimize=True)
    raw.unlink()
    size = png.stat().st_size
    print(f"{png.relative_to(ROOT)}: {size / 1000:.0f} kB")
    if size > MAX_BYTES:
        raise SystemExit(f"{png}: {size} bytes, more than {MAX_BYTES}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("out/screenshots"),
                   help="the runs' outputs, relative to the checkout (default out/screenshots)")
    p.add_argument("--browser", default="chromium", help="a Chromium binary (default: chromium on the PATH)")
    args = p.parse_args()
    if shutil.which(args.browser) is None:
        raise SystemExit(f"{args.browser} not found: install it from the OS packages (apt-get install chromium)")
    work = args.work if args.work.is_absolute() else ROOT / args.work
    work.mkdir(parents=True, exist_ok=True)
    OUT.mkdir(parents=True, exist_ok=True)
    w = str(args.work)  # as given: relative to the checkout, where dt runs
    dt("demo", "--config", "configs/demo_thermal.yaml", "--quick", "--out", f"{w}/thermal")
    dt("calibrate", "--campaign", f"{w}/thermal/campaign", "--effects", "geometric,thermal",
       "--out", f"{w}/twin_thermal")
    dt("simulate", "--scenario", "configs/scenarios/hidden/backlash.yaml", "--out", f"{w}/bl.csv")
    dt("fit", "--data", f"{w}/bl.csv", "--out", f"{w}/m0")
    dt("fit", "--data", f"{w}/bl.csv", "--effects", "geometric", "--out", f"{w}/m1")
    dt("fit", "--data", f"{w}/bl.csv", "--effects", "geometric,backlash", "--out", f"{w}/m2")
    dt("compare", "--data", f"{w}/bl.csv", "--model", f"{w}/m0", "--model", f"{w}/m1", "--model", f"{w}/m2",
       "--names", "paper GPR,+geometric,+backlash", "--cv", "5", "--report", f"{w}/compare")
    shoot(args.browser, work / "thermal" / "report.html", OUT / "demo.png")
    shoot(args.browser, work / "twin_thermal" / "report.html", OUT / "calibrate.png")
    shoot(args.browser, work / "compare" / "report.html", OUT / "compare.png")


if __name__ == "__main__":
    main()
