"""Take the operator console's screenshots for docs/console.md from a run on the simulated cell.

    .venv/bin/python tools/console_screenshots.py        # writes docs/img/console-*.png

It starts a simulated cell and `hil serve` on loopback, drives the page in headless Chromium (the Debian
package chromium-headless-shell, as the tests do) through a registration: the plan before the start, the
operator's prompt, a second browser watching the run, and the finished run with its campaign in the history;
then a coarse grid on the same campaign with the drift monitor on: the deviation of every point and the
reference poses' drift (the simulated arm and hall warm up as the run goes).
About two minutes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from playwright.sync_api import Page, expect, sync_playwright

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "img"
PORT = 18036  # loopback only
WAIT_MS = 60_000
WARMING = ("--effects", "gravity_compliance,thermal_expansion")  # the arm and the hall warm: drift to show


def main() -> int:
    sys.path.insert(0, str(ROOT))
    from fakes.launch import sim_cell
    from hil.commands.sim_cell import write_sim_cell
    from tests.chromium import launch_chromium

    expect.set_options(timeout=WAIT_MS)
    with tempfile.TemporaryDirectory() as folder, sim_cell(time_scale=10.0, extra_args=WARMING) as cell:
        cell_toml = Path(folder) / "cell.toml"
        write_sim_cell(cell_toml, cell.info, cell.control.call("ground_truth"), 10.0)
        with cell_toml.open("a") as toml:  # reference poses between the grid's points, for the drift plot
            toml.write("\n[drift_monitor]\nposes = 2\nevery_points = 3\n")
        command = [sys.executable, "-m", "hil", "serve", "--cell", str(cell_toml), "--campaigns", folder]
        server = subprocess.Popen(
            [*command, "--port", str(PORT)], stdout=subprocess.PIPE, text=True, cwd=ROOT, env=os.environ
        )
        try:
            assert server.stdout is not None
            print(server.stdout.readline().strip())  # the console's address, once it is configured
            with sync_playwright() as playwright:
                browser = launch_chromium(playwright)
                page = browser.new_page(viewport={"width": 1400, "height": 1000})
                page.goto(f"http://127.0.0.1:{PORT}/", wait_until="networkidle")
                take(page, "plan", lambda: plan(page))
                page.click("#start")
                expect(page.locator("#prompt-text")).to_have_text("Put SMR 1 in tool nest 1.")
                take(page, "prompt")
                page.click("#prompt-done")
                expect(page.locator("#prompt-text")).to_contain_text("Guide the tracker's beam")
                page.click("#prompt-done")
                watcher = browser.new_page(viewport={"width": 1400, "height": 1000})
                watcher.goto(f"http://127.0.0.1:{PORT}/")
                expect(watcher.locator("#progress")).to_contain_text("points, ETA")
                expect(watcher.locator("#plot-note")).to_contain_text("points measured")
                take(watcher, "watching")
                expect(page.locator("#phase")).to_have_text("finished")
                wait_for_plotted(page, "plot", 12)
                take(page, "finished")
                grid(page)
                take(page, "drift")
                browser.close()
        finally:
            server.terminate()
            server.wait(30)
    return 0


def plan(page: Page) -> None:
    page.select_option("#procedure", "registration")
    page.fill("#campaign", "cell-a.sqlite")
    page.click("#check")
    expect(page.locator("#plan-poses")).to_have_text("12")


def grid(page: Page) -> None:
    """A coarse grid with validation poses on the registered campaign, run to its end."""
    page.select_option("#procedure", "grid_sampling")
    page.fill("#campaign", "cell-a.sqlite")
    page.fill("#f-step_m", "250")
    page.fill("#f-validation", "6")
    page.click("#check")
    page.click("#start")
    expect(page.locator("#prompt-text")).to_have_text("Put SMR 1 in tool nest 1.")
    page.click("#prompt-done")
    expect(page.locator("#phase")).to_have_text("finished")
    expect(page.locator("#drift-box")).to_be_visible()


def wait_for_plotted(page: Page, plot: str, count: int) -> None:
    """Until the plot (plotly.js's graph div) carries `count` points."""
    page.wait_for_function(
        "([id, n]) => (document.getElementById(id).data || []).reduce((k, t) => k + t.y.length, 0) === n",
        arg=[plot, count],
    )


def take(page: Page, name: str, before=None) -> None:
    if before is not None:
        before()
    path = IMAGES / f"console-{name}.png"
    page.screenshot(path=str(path), full_page=True)
    print(f"wrote {path.relative_to(ROOT)}")


if __name__ == "__main__":
    raise SystemExit(main())
