"""A real headless browser for the dashboard's tests and benchmark: the OS's Chromium (Debian's
package, /usr/bin/chromium) driven by Playwright for Python. Playwright's own browser download
(`playwright install`) is never used: CI has no network but the package registries, and .ci/run
installs the OS package when it is missing."""
from __future__ import annotations

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
    """Headless Chromium of the OS, launched by Playwright. A test that asks for it on a machine
    without one fails, saying what to install: the browser tests are never skipped silently."""
    try:
        exe = chromium_path()
    except RuntimeError as exc:
        import pytest  # only the tests launch through here (the benchmark opens its own profile)

        pytest.fail(str(exc))
    return playwright.chromium.launch(executable_path=exe, headless=True)


def processes_memory_mb(marker: str) -> dict[str, float]:
    """Memory (MB) of every process whose command line holds `marker` (a browser's profile
    directory: all its processes, renderer and GPU included), from /proc: `rss` summed (counts the
    pages the processes share once per process) and `pss` summed (shares them out: the browser's
    real cost)."""
    kb = {"rss": 0, "pss": 0}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if marker not in (d / "cmdline").read_bytes().decode(errors="replace"):
                continue
            for line in (d / "smaps_rollup").read_text().splitlines():
                name, _, rest = line.partition(":")
                if name in ("Rss", "Pss"):
                    kb[name.lower()] += int(rest.split()[0])
        except OSError:
            continue
    return {k: v / 1024 for k, v in kb.items()}


def canvas_ink(page, selector: str) -> dict:
    """How much of a canvas is drawn: `drawn`, pixels that differ from its top-left (background)
    pixel; `grey`, dark neutral pixels (the arm's links and joints); `pixels`, all of them."""
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


def canvas_colour(page, selector: str, rgb: tuple[int, int, int], tol: int = 40) -> int:
    """Pixels of a canvas within `tol` (sum of |channel differences|) of the colour `rgb`."""
    return page.evaluate("""([sel, [r, g, b], tol]) => {
        const c = document.querySelector(sel), d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4) {
            if (Math.abs(d[i] - r) + Math.abs(d[i + 1] - g) + Math.abs(d[i + 2] - b) <= tol && d[i + 3] > 0) n++;
        }
        return n;
    }""", [selector, list(rgb), tol])
