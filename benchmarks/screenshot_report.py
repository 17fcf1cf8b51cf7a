"""Render a run's index.html in headless Chromium at a 1280 px window and check that it fits.

    .venv/bin/python benchmarks/screenshot_report.py reports/NAME [--width 1280] [--png report.png]

Prints the page's width against the window's, the tables that scroll inside their box, and any
element that sticks out of the window; writes a full-page screenshot. Exit status 0 when the
page is no wider than the window, 1 when it is wider, 2 on bad input (no index.html, no
Chromium). Needs Chromium (Debian: ``apt-get install -y chromium``); nothing is downloaded.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars"]

# Appended to a copy of the page: after layout, the measurements go into the DOM that --dump-dom prints.
PROBE = """<script>
window.addEventListener("load", () => {
  const inBox = el => el.closest(".tablebox") && !el.classList.contains("tablebox");
  const sticksOut = el => el.getBoundingClientRect().right > window.innerWidth + 0.5;
  // the outermost elements that stick out (their children would only repeat them)
  const out = [...document.querySelectorAll("body *")].filter(el => !inBox(el) && sticksOut(el)
      && !(el.parentElement && el.parentElement !== document.body && sticksOut(el.parentElement)))
    .map(el => el.tagName.toLowerCase() + (el.className ? "." + el.className : "") + " right="
         + Math.round(el.getBoundingClientRect().right));
  const boxes = [...document.querySelectorAll(".tablebox")];
  const m = {window: window.innerWidth, page: document.documentElement.scrollWidth,
             height: document.documentElement.scrollHeight, tables: boxes.length,
             scrolling: boxes.filter(b => b.scrollWidth > b.clientWidth + 0.5).length, outside: out.slice(0, 20)};
  const pre = document.createElement("pre");
  pre.id = "layout-probe";
  pre.textContent = "LAYOUT" + JSON.stringify(m) + "LAYOUT";
  document.body.appendChild(pre);
});
</script>"""


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    raise FileNotFoundError("no Chromium found; install it (Debian: apt-get install -y chromium)")


def _browser(args: list[str], profile: Path, width: int, height: int) -> str:
    cmd = [chromium(), *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}", *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    if done.returncode != 0:
        raise RuntimeError(f"chromium exited with {done.returncode}: {done.stderr[-2000:]}")
    return done.stdout


def measure(index: Path, width: int = 1280, png: Path | None = None) -> dict:
    """Layout figures of ``index`` at ``width`` px: window and page width, tables, scrolling tables,
    elements outside the window; a full-page screenshot to ``png`` when given."""
    html = index.read_text(encoding="utf-8")
    with tempfile.TemporaryDirectory(prefix="sotif-screenshot-") as tmp:
        tmp = Path(tmp)
        probe = tmp / "index.html"
        probe.write_text(html.replace("</body>", PROBE + "</body>"), encoding="utf-8")
        dom = _browser(["--dump-dom", probe.as_uri()], tmp / "profile-dom", width, 900)
        found = re.search(r"LAYOUT(\{.*?\})LAYOUT", dom)
        if not found:
            raise RuntimeError("the page did not report its layout (did it load?)")
        figures = json.loads(found.group(1))
        if png is not None:  # a window as tall as the page, so that one screenshot shows all of it
            _browser([f"--screenshot={png.resolve()}", index.resolve().as_uri()], tmp / "profile-png", width,
                     min(figures["height"], 16000))
    return figures


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", help="a run folder holding index.html (or the path of an HTML file)")
    p.add_argument("--width", type=int, default=1280, help="window width in CSS pixels (default 1280)")
    p.add_argument("--png", help="full-page screenshot to write (default: RUN_DIR/screenshot.png)")
    a = p.parse_args(argv)
    path = Path(a.run_dir)
    index = path if path.is_file() else path / "index.html"
    try:
        if not index.is_file():
            raise FileNotFoundError(f"{index}: file not found")
        png = Path(a.png) if a.png else index.parent / "screenshot.png"
        m = measure(index, a.width, png)
    except (FileNotFoundError, RuntimeError, subprocess.TimeoutExpired) as e:
        print(f"screenshot_report: error: {e}", file=sys.stderr)
        return 2
    fits = m["page"] <= m["window"]
    print(f"{index}: page {m['page']} px wide in a {m['window']} px window: {'fits' if fits else 'TOO WIDE'}; "
          f"{m['tables']} tables, {m['scrolling']} scroll inside their box; screenshot {png}")
    for line in m["outside"]:
        print(f"  outside the window: {line}")
    return 0 if fits else 1


if __name__ == "__main__":
    sys.exit(main())
