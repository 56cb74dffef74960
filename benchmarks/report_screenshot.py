"""What a person sees first of ``report.html``: render it in a headless browser and check it.

Usage::

    python -m benchmarks.report_screenshot out/run/report.html --png docs/report.png
    python -m benchmarks.report_screenshot out/run/report.html --browser /usr/bin/chromium

Opens the page in Chromium through Playwright (``pip install playwright``; the browser is
the system's Chromium, e.g. Debian's ``apt-get install chromium``, or Playwright's own)
in a window of 1280 x 1000 pixels and checks that the first 1000 pixels of height show

* the trajectory figure (against the ground truth when the run had one, else the top
  view of the trajectory and map), whole and loaded;
* the five numbers: frames tracked, ATE, fps, loops closed, keyframes.

Saves that first screen as a PNG (``--png``, default ``report_first_screen.png`` beside the
page); prints one line per check; exit code 1 when a check fails, 2 when no browser can be
started.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

#: the ids of the five numbers in report.html
NUMBERS = ("frames-tracked", "ate-rmse", "fps", "loops-closed", "keyframes")
#: the trajectory figure, in order of preference
TRAJECTORY_FIGURES = ("figures/ground_truth.png", "figures/map_top.png")
WIDTH, HEIGHT = 1280, 1000


class NoBrowser(RuntimeError):
    """Playwright or a Chromium to drive is missing."""


def find_chromium() -> str | None:
    """A Chromium on the PATH (Debian's ``chromium``, ``chromium-browser``, Chrome), or None
    (then Playwright's own browser is tried)."""
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def first_screen(report: Path, png: Path, browser: str | None = None) -> list[tuple[str, bool, str]]:
    """Render ``report`` at 1280 x 1000, save the first screen to ``png`` and check it.

    Returns
    -------
    list of (check, passed, detail)
        One per number (its box lies within the first 1000 pixels; it shows a dash when
        the run does not know it, e.g. the ATE without ground truth) and one for the
        trajectory figure (loaded and wholly within them).

    Raises
    ------
    NoBrowser
        Playwright is not installed or no Chromium can be started.
    """
    try:
        from playwright.sync_api import Error as PlaywrightError
        from playwright.sync_api import sync_playwright
    except ImportError:
        raise NoBrowser("playwright is not installed (pip install playwright)") from None
    exe = browser or find_chromium()
    checks: list[tuple[str, bool, str]] = []
    with sync_playwright() as p:
        try:
            b = p.chromium.launch(executable_path=exe, args=["--no-sandbox"])
        except PlaywrightError as exc:
            raise NoBrowser(f"no Chromium could be started ({str(exc).splitlines()[0]})") from None
        try:
            page = b.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(report.resolve().as_uri(), wait_until="load")
            boxes = page.evaluate("""() => Object.fromEntries([...document.querySelectorAll('[data-number]')].map(
                e => [e.dataset.number, {text: e.innerText.replace(/\\s+/g, ' ').trim(),
                                         bottom: e.getBoundingClientRect().bottom}]))""")
            for n in NUMBERS:
                box = boxes.get(n)
                ok = box is not None and box["bottom"] <= HEIGHT
                checks.append((f"number {n}", ok, "missing" if box is None else
                               f"'{box['text']}' ends at {box['bottom']:.0f} px"))
            img = None
            for src in TRAJECTORY_FIGURES:
                img = page.evaluate("""src => { const e = document.querySelector(`img[src="${src}"]`);
                    if (!e) return null; const r = e.getBoundingClientRect();
                    return {src: src, top: r.top, bottom: r.bottom, width: e.naturalWidth}; }""", src)
                if img is not None:
                    break
            ok = img is not None and img["width"] > 0 and img["top"] >= 0 and img["bottom"] <= HEIGHT
            checks.append(("trajectory figure", ok, "missing" if img is None else
                           f"{img['src']} from {img['top']:.0f} to {img['bottom']:.0f} px"
                           + ("" if img["width"] > 0 else ", not loaded")))
            png.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(png))  # the viewport: the first screen
        finally:
            b.close()
    return checks


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="report.html of an eifslam run")
    ap.add_argument("--png", type=Path, default=None, help="where to save the first screen")
    ap.add_argument("--browser", default=None, help="Chromium executable (default: found on the PATH)")
    args = ap.parse_args(argv)
    if not args.report.is_file():
        print(f"report_screenshot: {args.report}: not found", file=sys.stderr)
        return 1
    png = args.png or args.report.parent / "report_first_screen.png"
    try:
        checks = first_screen(args.report, png, args.browser)
    except NoBrowser as exc:
        print(f"report_screenshot: {exc}", file=sys.stderr)
        return 2
    for name, ok, detail in checks:
        print(f"{'ok  ' if ok else 'FAIL'} {name}: {detail}")
    print(f"first screen ({WIDTH}x{HEIGHT}) saved to {png}")
    return 0 if all(ok for _, ok, _ in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
