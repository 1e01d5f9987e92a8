"""A real headless browser for the dashboard's tests and benchmark: the OS's Chromium (Debian's
package, /usr/bin/chromium) driven by Playwright for Python. Playwright's own browser download
(`playwright install`) is never used: CI has no network but the package registries, and .ci/run
installs the OS package when it is missing."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

NAMES = ("chromium", "chromium-browser")


def chromium_path() -> str:
    """The OS Chromium's executable; RuntimeError saying how to install it when there is none."""
    for name in NAMES:
        found = shutil.which(name)
        if found:
            return found
    raise RuntimeError("no Chromium executable on PATH (looked for " + ", ".join(NAMES) + "): install the OS "
                       "package (`apt-get install -y chromium`; .ci/run does it as root); the dashboard's browser "
                       "tests drive it with Playwright and never download a browser")


def launch(playwright):
    """Headless Chromium of the OS, launched by Playwright."""
    return playwright.chromium.launch(executable_path=chromium_path(), headless=True)


def processes_rss_mb(marker: str) -> float:
    """Resident memory (MB) of every process whose command line holds `marker` (a browser's
    profile directory: all its processes, renderer and GPU included), summed from /proc."""
    total_kb = 0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if marker not in (d / "cmdline").read_bytes().decode(errors="replace"):
                continue
            for line in (d / "status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total_kb += int(line.split()[1])
        except OSError:
            continue
    return total_kb / 1024


def self_rss_mb() -> float:
    for line in Path(f"/proc/{os.getpid()}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def canvas_ink(page, selector: str) -> dict:
    """How much of a canvas is drawn: pixels that differ from its top-left (background) pixel,
    and those close to a colour the caller names later (returned raw: counts by rounded colour
    are too many, so only `drawn` and the pixel count)."""
    return page.evaluate("""(sel) => {
        const c = document.querySelector(sel), g = c.getContext('2d');
        const d = g.getImageData(0, 0, c.width, c.height).data;
        let drawn = 0, grey = 0;
        const [r0, g0, b0] = [d[0], d[1], d[2]];
        for (let i = 0; i < d.length; i += 4) {
            if (Math.abs(d[i] - r0) + Math.abs(d[i + 1] - g0) + Math.abs(d[i + 2] - b0) > 30) drawn++;
            // the arm's links (#56606a, #9aa5ae) and joints (#3d454c): greys darker than the floor grid
            if (Math.abs(d[i] - d[i + 2]) < 30 && d[i] < 170 && d[i + 3] > 0) grey++;
        }
        return {drawn, grey, pixels: d.length / 4};
    }""", selector)
