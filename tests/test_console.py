"""The operator console (`hil serve`) driven in headless Chromium: one simulated cell, one console server and one
browser for the whole module. The page starts a registration from its form, shows the plan and the progress,
takes the operator's answers (a reloaded page finds its prompt waiting), pauses, resumes, aborts (every
recorded point kept) and resumes the campaign; its plots (plotly.js) carry every measured point and the drift
monitor's reference poses, rebuilt from the campaign in a reloaded page and a second browser; a second browser only watches; `hil run` on a campaign the
console drives is refused with who holds it, and the reverse; a console with a token refuses requests
without it; `hil serve` off loopback without a token refuses to start."""

from __future__ import annotations

import dataclasses
import re
import socket
import sqlite3
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import closing, contextmanager
from pathlib import Path

import numpy as np
import pytest
from chromium import CHROMIUM, launch_chromium
from playwright.sync_api import Browser, Page, expect, sync_playwright
from sim_session import running_cell

from hil.cli import main
from hil.console.app import CLIENT_COOKIE, TOKEN_COOKIE, ConsoleOptions, build_app
from hil.console.station import CONTROL_LAPSE_S, Station
from hil.console.views import reference_poses
from hil.data.campaign_lock import CampaignLock, Holder
from hil.data.store import CampaignStore
from hil.runner.procedure import ParameterError, from_user_values
from hil.runner.registry import load

pytestmark = pytest.mark.sim

WAIT_MS = 30_000  # a page state the run must reach (the simulated cell runs 20x faster than real time)
DIAGNOSIS_WAIT_MS = 100_000  # `hil diagnose` in its own process: 3 s alone, over 30 s on a loaded machine
POSES = 12
expect.set_options(timeout=WAIT_MS)
CAMPAIGN = "console.sqlite"
DRIFT_POSES, DRIFT_EVERY = (
    2,
    4,
)  # the drift monitor of the module's cell: 2 reference poses every 4 grid points


@contextmanager
def console_server(station: Station, options: ConsoleOptions) -> Iterator[str]:
    """The console on uvicorn in a thread, on a loopback socket bound here (listening before the server
    starts: a request waits in the backlog, no polling for readiness); yields its URL."""
    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(16)
    server = uvicorn.Server(
        uvicorn.Config(build_app(station, options), log_level="warning", timeout_graceful_shutdown=1)
    )
    thread = threading.Thread(
        target=server.run, kwargs={"sockets": [sock]}, name="console-server", daemon=True
    )
    thread.start()
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(20)
        sock.close()


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    folder = tmp_path_factory.mktemp("console")
    with running_cell(folder, time_scale=20.0) as (_, config):
        yield folder, config


@pytest.fixture(scope="module")
def console(cell) -> Iterator[tuple[str, Station]]:
    folder, config = cell
    config = dataclasses.replace(config, drift_poses=DRIFT_POSES, drift_every_points=DRIFT_EVERY)
    station = Station(config, folder, address="the test's console")
    with console_server(station, ConsoleOptions()) as url:
        yield url, station


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: tools/system-deps installs it (make runs it)")
    with sync_playwright() as playwright:
        chromium = launch_chromium(playwright, timeout=120_000)
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def page_errors() -> list[str]:
    """The errors the module's pages threw (a plot that failed to draw throws here)."""
    return []


@pytest.fixture(scope="module")
def operator_page(browser, console, page_errors) -> Iterator[Page]:
    """The controlling browser's page (the first to open the console takes control)."""
    context = browser.new_context()
    page = context.new_page()
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    page.set_default_timeout(WAIT_MS)
    page.goto(console[0])
    expect(page.locator("#control")).to_have_text("This browser controls the console.")
    yield page
    context.close()


@pytest.fixture(scope="module")
def watcher_page(browser, console, operator_page, page_errors) -> Iterator[Page]:
    """A second browser's page, opened after the controller's (a new browser context loads plotly.js afresh:
    a second or two, so the module opens one)."""
    context = browser.new_context()
    page = context.new_page()
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    page.set_default_timeout(WAIT_MS)
    yield page
    context.close()


def fill_registration(page: Page, poses: str) -> None:
    page.select_option("#procedure", "registration")
    page.fill("#campaign", CAMPAIGN)
    page.fill("#f-poses", poses)


def measured(campaign: Path) -> list[tuple[int, str]]:
    with CampaignStore(campaign, create=False) as store:
        df = store.measurement_columns(("point_id",))
    return list(zip(df["id"].tolist(), df["point_id"].tolist(), strict=True))


def plotted(page: Page, plot: str, count: int) -> list[dict]:
    """The traces plotly.js draws in the page's `#plot` (the graph div's own `data`), once they carry `count`
    points: each trace's name, axes and points (x, y, the point ids)."""
    traces = "(id) => (document.getElementById(id).data || [])"
    page.wait_for_function(
        f"([id, n]) => ({traces})(id).reduce((k, t) => k + t.y.length, 0) === n", arg=[plot, count]
    )
    return page.evaluate(
        f"(id) => ({traces})(id).map((t) => ({{name: t.name, xaxis: t.xaxis || 'x', x: Array.from(t.x), "
        "y: Array.from(t.y), ids: Array.from(t.text)}))",
        plot,
    )


def test_a_bad_value_is_refused_with_the_command_lines_message(operator_page):
    with pytest.raises(ParameterError) as refused:
        from_user_values(load("registration"), {"poses": 3})
    fill_registration(operator_page, "3")
    operator_page.click("#check")
    expect(operator_page.locator("#refusal")).to_contain_text(str(refused.value))
    expect(operator_page.locator("#start")).to_be_disabled()


def test_the_plan_is_shown_before_the_start(operator_page):
    fill_registration(operator_page, str(POSES))
    operator_page.click("#check")
    expect(operator_page.locator("#plan-poses")).to_have_text(str(POSES))
    expect(operator_page.locator("#plan-envelope")).to_contain_text("every pose passed the envelope")
    expect(operator_page.locator("#plan-duration")).to_have_text(re.compile(r"\d+\.\d min"))
    expect(operator_page.locator("#start")).to_be_enabled()


def answer_prompt(page: Page, text: str) -> None:
    expect(page.locator("#prompt-text")).to_have_text(text)
    page.click("#prompt-done")
    expect(page.locator("#prompt-text")).not_to_have_text(text)


def test_a_run_from_the_form_with_prompts_pause_resume_and_abort(operator_page, cell, capsys):
    page, folder = operator_page, cell[0]
    page.click("#start")
    answer_prompt(page, "Put SMR 1 in tool nest 1.")
    expect(page.locator("#prompt-text")).to_have_text(re.compile("Guide the tracker's beam"))
    page.reload()  # a browser that comes back finds the prompt still waiting
    answer_prompt(page, "Guide the tracker's beam onto SMR 1 on the tool until it locks.")
    expect(page.locator("#progress")).to_contain_text(
        re.compile(rf"registration: [1-9]\d* of {POSES} points")
    )
    page.click("#pause")
    expect(page.locator("#phase")).to_have_text("paused")
    expect(page.locator("#resume")).to_be_enabled()
    expect(page.locator("#robot-mode")).to_have_text("RUNNING / NORMAL")  # read by the run between points
    expect(page.locator("#tracker")).to_contain_text("last measured")
    held = len(measured(folder / CAMPAIGN))
    assert held < POSES

    # while the console drives the campaign, `hil run` on it is refused with who holds it
    code = main(
        ["run", "registration", "--cell", str(folder / "cell.toml"), "--campaign", str(folder / CAMPAIGN)]
    )
    assert code != 0
    assert "is driven by hil serve registration at the test's console (process" in capsys.readouterr().err

    page.click("#resume")
    expect(page.locator("#phase")).to_have_text("running")
    page.click("#pause")
    expect(page.locator("#phase")).to_have_text("paused")
    page.click("#abort")
    expect(page.locator("#phase")).to_have_text("stopped")
    expect(page.locator("#message")).to_contain_text("every recorded point is kept")
    kept = measured(folder / CAMPAIGN)
    assert held <= len(kept) < POSES
    with CampaignStore(folder / CAMPAIGN, create=False) as store:
        assert "interrupted" in store.events()["kind"].tolist()

    # the same start resumes: the operator sets up again, the recorded points are not measured again
    fill_registration(page, str(POSES))  # the reloaded page shows the form afresh
    page.click("#check")
    expect(page.locator("#start")).to_be_enabled()
    page.click("#start")
    answer_prompt(page, "Put SMR 1 in tool nest 1.")
    answer_prompt(page, "Guide the tracker's beam onto SMR 1 on the tool until it locks.")
    expect(page.locator("#phase")).to_have_text("finished")
    expect(page.locator("#message")).to_contain_text(f"of {POSES} points agree")
    after = measured(folder / CAMPAIGN)
    assert len(after) == POSES and after[: len(kept)] == kept
    (trace,) = plotted(page, "plot", POSES)  # one point per measured point, in measuring order
    assert trace["name"] == "registration" and trace["ids"] == [point_id for _, point_id in after]
    assert trace["x"] == list(range(1, POSES + 1))
    assert all(0.0 < d < 5.0 for d in trace["y"])  # mm from the nominal model: the simulated arm's errors
    expect(page.locator("#drift-box")).to_be_hidden()  # no reference poses in a registration


def test_a_grid_plots_its_points_and_the_reference_poses_drift_in_a_reloaded_page_and_a_second_browser(
    operator_page, watcher_page, console, cell, page_errors
):
    """A grid with the drift monitor on a registered campaign: the deviation plot carries every measured point
    of both procedures, the drift plot each reference pose's readings against time and temperature (0 at its
    first reading); a page reloaded mid-run and a second browser opened mid-run draw what the store holds."""
    page, folder = operator_page, cell[0]
    campaign = folder / "drift.sqlite"
    with (
        closing(sqlite3.connect(folder / CAMPAIGN)) as registered,
        closing(sqlite3.connect(campaign)) as copy,
    ):
        registered.backup(copy)  # the registered campaign of the run above, whole
    page.select_option("#procedure", "grid_sampling")
    page.fill("#campaign", campaign.name)
    page.fill("#f-step_m", "500")
    page.fill("#f-box_min_m", "0 500 300")  # two grid points: reference rounds before and after them
    page.fill("#f-box_max_m", "500 520 320")
    page.fill("#f-validation", "0")
    page.click("#check")
    page.click("#start")
    answer_prompt(page, "Put SMR 1 in tool nest 1.")
    expect(page.locator("#progress")).to_contain_text(re.compile(r": [1-9]\d* of \d+ points"))
    page.click("#pause")  # held mid-run: the store stands still while the pages are read
    expect(page.locator("#phase")).to_have_text("paused")
    page.reload()
    watcher = watcher_page
    watcher.goto(console[0])
    held = [point_id for _, point_id in measured(campaign)]
    assert len(held) > POSES  # the registration's and some of the grid's
    for reader in (page, watcher):
        assert sum((t["ids"] for t in plotted(reader, "plot", len(held))), []) == held
    page.click("#resume")
    expect(page.locator("#phase")).to_have_text("finished")
    with CampaignStore(campaign, create=False) as store:
        df = store.measurements()
    deviations = plotted(page, "plot", len(df))
    assert [t["name"] for t in deviations] == ["registration", "grid_sampling"]
    assert sum((t["ids"] for t in deviations), []) == df["point_id"].tolist()
    assert plotted(watcher, "plot", len(df)) == deviations

    references = df[df["step"] == "reference"]
    assert len(references) >= 2 * DRIFT_POSES  # before and after the grid at least
    drifts = plotted(page, "drift", 2 * len(references))  # each reading against time and temperature
    assert plotted(watcher, "drift", 2 * len(references)) == drifts
    poses = reference_poses(references)
    p_tracker_mm = np.stack(references["p_tracker_m"].to_list()) * 1e3
    for axis in ("x", "x2"):
        by_pose = {t["name"]: t for t in drifts if t["xaxis"] == axis}
        assert sorted(by_pose) == sorted(set(poses)) and len(by_pose) == DRIFT_POSES
        for pose, trace in by_pose.items():
            rows = poses == pose
            assert trace["ids"] == references.loc[rows, "point_id"].tolist()
            moved_mm = np.linalg.norm(p_tracker_mm[rows] - p_tracker_mm[rows][0], axis=1)
            np.testing.assert_allclose(trace["y"], moved_mm, atol=2e-4)
            assert trace["y"][0] == 0.0
    expect(page.locator("#drift .xtitle").first).to_contain_text("(s)")
    expect(page.locator("#drift .x2title")).to_contain_text("(°C)")
    page.select_option("#plot-x", "time")
    expect(page.locator("#plot .xtitle")).to_have_text("time since the campaign's first point (s)")
    by_time = plotted(page, "plot", len(df))
    times = np.concatenate([t["x"] for t in by_time])
    assert np.all(np.diff(times) >= 0) and times[0] == 0.0
    assert page_errors == []


def test_a_campaign_hil_run_drives_is_refused_by_the_console(operator_page, console, cell):
    """The reverse of the refusal checked in the run above: a campaign `hil run` holds is refused by the
    console's start, naming the run; nothing is written to it."""
    campaign = cell[0] / "held.sqlite"
    body = {"procedure": "registration", "campaign": campaign.name, "values": {}}
    with CampaignLock(campaign, Holder.this_process("hil run registration")):
        refused = operator_page.request.post(console[0] + "/api/start", data=body)
    assert refused.status == 409
    assert "is driven by hil run registration (process" in refused.json()["message"]
    assert not campaign.exists()


def test_the_campaign_is_in_the_history(operator_page):
    row = operator_page.locator(f"#history tr[data-campaign='{CAMPAIGN}']")
    expect(row).to_contain_text(f"registration ({POSES})")


def test_abort_while_a_prompt_waits_stops_the_run_before_anything_is_measured(operator_page, cell):
    page, campaign = operator_page, cell[0] / "aborted.sqlite"
    fill_registration(page, str(POSES))
    page.fill("#campaign", campaign.name)
    page.click("#check")
    page.click("#start")
    expect(page.locator("#prompt-text")).to_have_text("Put SMR 1 in tool nest 1.")
    page.click("#abort")
    expect(page.locator("#phase")).to_have_text("stopped")
    expect(page.locator("#prompt")).to_be_hidden()
    assert measured(campaign) == []
    with CampaignStore(campaign, create=False) as store:
        assert store.events()["kind"].tolist()[-1] == "interrupted"


def test_diagnosis_from_the_page_says_why_it_cannot_run_on_a_registration(operator_page):
    """Diagnose runs `hil diagnose` on the campaign; on one without a grid its refusal reaches the page."""
    row = operator_page.locator(f"#history tr[data-campaign='{CAMPAIGN}']")
    row.get_by_role("button", name="Diagnose").click()
    refusal = expect(operator_page.locator("#refusal"))
    refusal.to_contain_text(f"the diagnosis of {CAMPAIGN} failed", timeout=DIAGNOSIS_WAIT_MS)
    expect(operator_page.locator("#refusal")).to_contain_text("no measurements of grid_sampling")
    expect(row).to_contain_text("–")  # no report link


def test_compensation_from_the_page_uses_the_diagnosed_model_and_links_the_joints(operator_page, console):
    """Compensate is refused until the campaign has a diagnosed model; with one it runs `hil compensate` on the
    campaign's validation targets and links the joints it wrote (each with its predicted remaining error)."""
    from calib_data import cell_datasets, record_validated_campaign, true_effect_model

    url, station = console
    refused = operator_page.request.post(f"{url}/api/compensate/{CAMPAIGN}", data={})
    assert refused.status == 409 and refused.json()["remedy"] == "diagnose it first"
    _, train, val = cell_datasets(step_m=0.2, n_val=4, seed=0)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    name = "validated.sqlite"
    with CampaignStore(station.campaigns / name) as store:  # a finished campaign with validation points
        record_validated_campaign(store, model, val)
    model.save(station.campaigns / f"{name}.model.json")  # what Diagnose writes beside the campaign
    operator_page.reload()
    row = operator_page.locator(f"#history tr[data-campaign='{name}']")
    row.get_by_role("button", name="Compensate").click()
    expect(row.get_by_role("link", name="compensated joints")).to_be_visible(timeout=DIAGNOSIS_WAIT_MS)
    written = (station.campaigns / f"{name}.compensated.csv").read_text().splitlines()
    assert len(written) == 1 + len(val) and "q1_rad" in written[0]
    assert all(",ok," in row for row in written[1:])  # every target reached by the model


def test_a_second_browser_watches_and_is_refused_control_until_it_is_released(
    watcher_page, console, operator_page
):
    page = watcher_page
    page.goto(console[0])
    expect(page.locator("#control")).to_have_text("Another browser controls this console: this one watches.")
    seen_by_controller = operator_page.locator("#run-name").text_content() or ""
    expect(page.locator("#run-name")).to_have_text(seen_by_controller)  # the same run
    expect(page.locator("#phase")).to_have_text(operator_page.locator("#phase").text_content() or "")
    expect(page.locator("#start")).to_be_disabled()
    refused = page.request.post(console[0] + "/api/abort", data={})
    assert refused.status == 403
    assert "another one controls the console" in refused.json()["message"]
    expect(page.locator("#take-control")).to_be_hidden()
    operator_page.click("#release-control")  # the controller lets go: the watcher may take over
    expect(operator_page.locator("#control")).to_have_text("Nobody controls the console.")
    page.click("#take-control")
    expect(page.locator("#control")).to_have_text("This browser controls the console.")
    expect(operator_page.locator("#control")).to_have_text(
        "Another browser controls this console: this one watches."
    )


def test_a_controlling_page_that_reloads_keeps_control_for_the_lapse_from_its_reload(cell, tmp_path):
    """Control lapses CONTROL_LAPSE_S after the controller's page went, counted from when its event stream
    closed (a reload), not from the stream's last state (sent only on a change or a keepalive): a page that
    reloads slowly on a busy machine finds its control again, and another browser gets it only after that."""
    now = [0.0]
    station = Station(cell[1], tmp_path, address="the test's console", clock=lambda: now[0])

    def request(url: str, client: str, data: bytes | None = None) -> urllib.request.Request:
        return urllib.request.Request(url, data=data, headers={"Cookie": f"{CLIENT_COOKIE}={client}"})

    with console_server(station, ConsoleOptions()) as url:
        with urllib.request.urlopen(request(url + "/api/control", "a", b"{}"), timeout=30) as answer:
            assert answer.status == 200
        with urllib.request.urlopen(request(url + "/api/stream", "a"), timeout=30) as stream:
            assert stream.readline().startswith(b"data: ")  # the page's first state, sent at 0 s
            now[0] = 25.0  # the page reloads 25 s later: its stream closes
        now[0] = 25.0 + CONTROL_LAPSE_S - 0.5
        deadline = time.monotonic() + 30
        while not station.controlled_by_another("b"):  # the state to wait for: the close seen by the server
            assert time.monotonic() < deadline, "control lapsed from the stream's last state, not its close"
            time.sleep(0.02)
        assert not station.claim("b") and station.claim("a")  # the reloaded page claims it back
        now[0] += CONTROL_LAPSE_S + 1.0  # a's page never came back this time
        assert station.claim("b")


def test_a_request_by_another_host_name_is_refused(console):
    """A page elsewhere that points its own name at 127.0.0.1 (DNS rebinding) cannot reach the console."""
    rebound = urllib.request.Request(console[0] + "/api/state", headers={"Host": "cell.example.com"})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(rebound, timeout=10)
    assert refused.value.code == 400
    with urllib.request.urlopen(console[0] + "/api/state", timeout=10) as state:
        assert state.status == 200


def test_a_console_with_a_token_refuses_requests_without_it(cell):
    folder, config = cell
    options = ConsoleOptions(token="s3cret-token", allowed_hosts=("*",))  # as hil serve off loopback
    with console_server(Station(config, folder), options) as url:
        for path in ("/", "/api/state", "/api/history", "/assets/plotly.min.js"):
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(url + path, timeout=10)
            assert refused.value.code == 401
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(url + "/api/state?token=wrong", timeout=10)
        with urllib.request.urlopen(url + "/?token=s3cret-token", timeout=10) as page:
            cookies = [c.split(";")[0] for c in page.headers.get_all("set-cookie")]
        cookie = next(c for c in cookies if c.startswith(TOKEN_COOKIE + "="))
        bearer = urllib.request.Request(url + "/api/state", headers={"Authorization": "Bearer s3cret-token"})
        with urllib.request.urlopen(bearer, timeout=10) as state:
            assert state.status == 200
        carried = urllib.request.Request(url + "/api/history", headers={"Cookie": cookie})
        with urllib.request.urlopen(carried, timeout=10) as history:
            assert history.status == 200
        script = urllib.request.Request(url + "/assets/plotly.min.js", headers={"Cookie": cookie})
        with urllib.request.urlopen(
            script, timeout=10
        ) as plotly_js:  # the page's plots, served by the console
            assert plotly_js.headers["Content-Type"].startswith("text/javascript")
            assert b"plotly.js v" in plotly_js.read(200)


def test_serve_off_loopback_without_a_token_is_refused_before_it_binds(cell, capsys):
    """Refused, and returned: a console that had bound would serve until stopped."""
    folder = cell[0]
    args = ["serve", "--cell", str(folder / "cell.toml"), "--campaigns", str(folder), "--host", "0.0.0.0"]
    assert main(args) != 0
    err = capsys.readouterr().err
    assert "--host 0.0.0.0 is not a loopback address and the console has no token" in err
    assert "nothing was bound" in err
