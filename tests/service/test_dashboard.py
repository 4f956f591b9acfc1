"""The browser dashboard (web/) in Debian's chromium, headless, driven by playwright.

Never downloads a browser: it launches /usr/bin/chromium (`.ci/run` installs it; without it
these tests fail, they do not skip). Against a live ``sdh2svc serve --sim`` (the ``service``
fixture): start a run on the egg, see the plots, heat maps and the 3-D view update, e-stop it,
release; a bad parameter shows the server's 422 message next to its field; a recorded run
replays with one scrubber driving plots, pads, sketch and the 3-D view, and its exports
download. At 1024×768 the pads and plots fit the first screen (the parameters in a drawer);
toasts expire, and clear once their problem is gone. A faulted run leaves a notice saying what
happened and offering Open hand; a service that dies (or freezes) greys the dashboard out under
a banner, and one that comes back restores it (its E-STOP is still tried, and says to use the
hand's own switch when it fails). An e-stop the hand has not confirmed, or the disk not taken,
is said in a banner; a custom object (``--object-file``) is run as it is. Every mutating request
the page makes carries a JSON body and its content type.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx
import playwright.async_api as playwright_api
import pytest
from playwright.async_api import expect

from sdh2svc.client import Conflict
from sdh2svc.config import load_config
from sdh2svc.model.hand import matrix_shapes
from sdh2svc.service.store import Recorder, RunStore
from tests.live_service import LiveService, start_run, start_service
from tests.service.test_replay_api import sample as replay_sample
from tests.service.test_replay_api import texels as replay_texels

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
RUN_TIMEOUT_MS = 120_000
# an expectation waits for its event up to this long (Playwright's default, 5 s, was once too
# short in CI for a refresh of the run history: chromium, the service and the other test worker
# share two cores); it only ever waits longer, it never passes sooner
expect.set_options(timeout=30_000)
ACTIVE = ("idle", "connecting", "pre-shape", "grasping", "rolling", "releasing")


# Pixels of a canvas that differ from a colour (RGB) and are opaque.
COUNT_PIXELS_NOT = """([sel, rgb]) => {
  const c = document.querySelector(sel);
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let n = 0;
  for (let i = 0; i < d.length; i += 4) {
    if (d[i + 3] === 255 && (d[i] !== rgb[0] || d[i + 1] !== rgb[1] || d[i + 2] !== rgb[2])) n++;
  }
  return n;
}"""
# Strongly coloured pixels of a canvas (plot lines; axes and grid are grey).
COUNT_COLOURED = """(sel) => {
  const c = document.querySelector(sel);
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let n = 0;
  for (let i = 0; i < d.length; i += 4) {
    const hi = Math.max(d[i], d[i + 1], d[i + 2]), lo = Math.min(d[i], d[i + 1], d[i + 2]);
    if (d[i + 3] > 128 && hi - lo > 80) n++;
  }
  return n;
}"""
PLOTS = ("joints", "force", "sigma", "s", "omega", "lambda")
# What the replay shows: the pads', the sketch's and each plot's iteration, the scrubber's label.
SHOWN = """() => ({
  pads: document.querySelector('#pads').dataset.iteration,
  sketch: document.querySelector('#sketch').dataset.iteration,
  objectPose: document.querySelector('#sketch').dataset.objectPose,
  readout: document.querySelector('#object-readout').dataset.iteration,
  readoutClass: document.querySelector('#object-readout').dataset.class,
  plots: [...document.querySelectorAll('.plot')].map(p => p.dataset.cursorIteration),
  cursors: window.sdh2debug.plots.charts.map(c => c.cursor.idx),
  index: window.sdh2.replayIndex,
  at: document.querySelector('#replay-at').textContent,
  padInfo: document.querySelectorAll('#pads .pad-info')[1].textContent,
})"""
PAUSE = """() => {
  if (document.querySelector('#replay-banner').dataset.playing === 'true')
    document.querySelector('#replay-play').click();
}"""
PAD_ZERO_RGB = [24, 27, 38]  # web/pads.js ZERO_COLOR: a taxel reading 0
MUTATING = ("POST", "PUT", "PATCH", "DELETE")
RUN_LIST = re.compile(r"/api/runs(\?|$)")  # GET /api/runs, with its query or without
SCREENSHOTS = os.environ.get("SDH2SVC_SCREENSHOTS")  # a directory: the tests leave PNGs there


@contextlib.asynccontextmanager
async def dashboard(
    svc: LiveService, *, token: str | None = None, lie: StatusLie | None = None
) -> AsyncIterator[Any]:
    """A headless chromium page on ``svc``'s dashboard (``token`` stored beforehand, as the token
    field does; ``lie`` between the page and the service's statuses); fails on any script error
    in the page."""
    async with playwright_api.async_playwright() as pw:
        browser = await pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            context = await browser.new_context(viewport={"width": 1500, "height": 1200})
            if token:
                await context.add_init_script(f"localStorage.setItem('sdh2svc.token', {token!r});")
            pg = await context.new_page()
            errors: list[str] = []
            pg.on("pageerror", lambda e: errors.append(str(e)))
            pg.on("request", lambda req: errors.extend(bad_request(req)))
            if lie is not None:
                await pg.route("**/api/status", lie.http)
                await pg.route_web_socket("**/ws/telemetry*", lie.ws)
            await pg.goto(svc.url + "/")
            await pg.wait_for_function(
                "window.sdh2 && window.sdh2.statusMsgs > 0 && window.sdh2.ws === 'open'",
                timeout=30_000,
            )
            await pg.wait_for_selector("#params-form input[name=k]", state="attached")
            yield pg
            assert errors == [], f"script errors on the dashboard: {errors}"
        finally:
            await browser.close()


class StatusLie:
    """While ``on``, every status the page gets (the telemetry socket's and GET /api/status's)
    says the hand has not confirmed the latched e-stop, as a silent joint line makes the service
    say (``estop.hand_reached`` false); the rest passes as it is."""

    def __init__(self) -> None:
        self.on = False

    def status(self, st: dict[str, Any]) -> dict[str, Any]:
        if self.on and st.get("estop"):
            st["estop"]["hand_reached"] = False
        return st

    def message(self, m: str | bytes) -> str | bytes:
        msg = json.loads(m)
        if msg.get("type") in ("hello", "status"):
            msg["status"] = self.status(msg["status"])
        return json.dumps(msg)

    async def http(self, route: Any) -> None:
        real = await route.fetch()
        await route.fulfill(response=real, json=self.status(await real.json()))

    def ws(self, ws: Any) -> None:
        server = ws.connect_to_server()
        server.on_message(lambda m: ws.send(self.message(m)))


def bad_request(req: Any) -> list[str]:
    """What is wrong with a request the page made: the service answers 415 to a mutating request
    without a JSON body and ``Content-Type: application/json``."""
    if req.method not in MUTATING:
        return []
    ctype = (req.headers.get("content-type") or "").split(";")[0].strip()
    try:
        json.loads(req.post_data or "")
    except ValueError:
        return [f"{req.method} {req.url}: body {req.post_data!r} is not JSON"]
    if ctype != "application/json":
        return [f"{req.method} {req.url}: content type {ctype!r}"]
    return []


async def screenshot(page: Any, name: str) -> None:
    if SCREENSHOTS:
        await page.screenshot(path=str(Path(SCREENSHOTS) / f"{name}.png"), full_page=False)


@pytest.fixture
async def page(service: LiveService) -> AsyncIterator[Any]:
    async with dashboard(service, token=service.token) as pg:
        yield pg


async def counters(page: Any) -> dict[str, Any]:
    return await page.evaluate("() => ({...window.sdh2})")  # type: ignore[no-any-return]


async def test_layout_and_static_assets(service: LiveService, page: Any) -> None:
    for sel in ("#start", "#stop", "#estop", "#estop-release", "#run-state", "#stroke",
                "#iteration", "#params-form", "#object-select", "#sketch", "#runs",
                "#viewer", "#bus-stats", "#errors"):  # fmt: skip
        assert await page.locator(sel).count() == 1, sel
    assert await page.locator("#pads canvas").count() == 6
    labels = await page.locator("#pads figcaption").all_inner_texts()
    assert [t.split(" (")[0] for t in labels] == [
        "F1 prox", "F1 dist", "thumb prox", "thumb dist", "F2 prox", "F2 dist"]  # fmt: skip
    for name in PLOTS:
        assert await page.locator(f"#plot-{name} .uplot canvas").count() == 1, name
    # offline: every script and style sheet comes from this server
    srcs = await page.evaluate(
        "() => [...document.querySelectorAll('script[src], link[href]')].map(e => e.src || e.href)"
    )
    assert srcs and all(s.startswith(service.url) or s.startswith("data:") for s in srcs), srcs
    async with httpx.AsyncClient(base_url=service.url) as http:
        for path in ("/web/vendor/uplot/uPlot.iife.min.js", "/web/vendor/uplot/LICENSE",
                     "/web/app.js", "/web/style.css"):  # fmt: skip
            assert (await http.get(path)).status_code == 200, path
    # the form shows the server's parameters; the object choice lists the presets
    params = httpx.get(service.url + "/api/params").json()
    assert float(await page.input_value("#params-form input[name=k]")) == params["k"]
    options = await page.locator("#object-select option").all_inner_texts()
    assert "egg" in options
    # the sketch's cones (and the event log's cone margins) open as wide as the sample says the
    # run widened them (Sample.alpha), else the run's α
    widths = await page.evaluate(
        "async () => { const m = await import('/web/sketch.js');"
        " return [m.coneAlpha({alpha: 35}, 22), m.coneAlpha({alpha: null}, 22),"
        " m.coneAlpha(undefined, 22)]; }"
    )
    assert widths == [35, 22, 22]
    # a dropped telemetry socket comes back by itself
    await page.evaluate("window.sdh2debug.telemetry.ws.close()")
    await page.wait_for_function(
        "window.sdh2.connects >= 2 && window.sdh2.ws === 'open'", timeout=15_000
    )
    assert await page.inner_text("#ws-state") == "live"
    assert (await counters(page))["lastError"] is None
    await lab_screen_toasts_and_the_parameter_drawer(page)


# What the sketch says of the object after each (run state, the sim's `dropped`): held; falls
# mid-roll: dropped (and stays so as the run releases); placed again; falls as it releases:
# released (and stays so once the run is done).
OBJECT_FATES = """() => {
  const d = window.sdh2debug;
  const base = structuredClone(d.status());
  const out = [];
  for (const [runState, dropped] of [['rolling', false], ['rolling', true], ['releasing', true],
                                     ['grasping', false], ['releasing', true], ['done', true]]) {
    const st = structuredClone(base);
    st.run = {...(st.run || {}), id: 99999, state: runState};
    d.onMessage({type: 'status', status: st});
    d.onMessage({type: 'sim', truth: {object: 'egg', held: !dropped, dropped, in_fixture: false,
                                      pose: [20, 120, 0], outline: [], contacts: []}});
    d.sketch.draw();
    out.push(document.querySelector('#sketch').dataset.object);
  }
  d.onMessage({type: 'status', status: base});
  return out;
}"""


# The boxes of the control bar, the pads and the six plots (viewport pixels).
BOXES = """() => {
  const box = (e) => {
    const r = e.getBoundingClientRect();
    return [r.top, r.bottom, r.left, r.right];
  };
  return { header: box(document.querySelector('#controls')),
           pads: box(document.querySelector('.pads-card')),
           plots: [...document.querySelectorAll('.plot')].map(box),
           canvases: [...document.querySelectorAll('.plot .uplot canvas')].map(box) };
}"""


# Every chart inside its plot's box.
FITTED = """() => [...document.querySelectorAll('.plot')].every((p) => {
  const r = p.getBoundingClientRect();
  const c = p.querySelector('.uplot').getBoundingClientRect();
  return c.right <= r.right && c.bottom <= r.bottom;
})"""


async def lab_screen_toasts_and_the_parameter_drawer(page: Any) -> None:
    """(In the layout test's page: no browser of its own.)"""
    # at 1024×768 and 1280×800 the pads and all six plots are on the first screen
    for width, height in ((1024, 768), (1280, 800)):
        await page.set_viewport_size({"width": width, "height": height})
        await page.evaluate("window.scrollTo(0, 0)")
        await page.wait_for_function(FITTED)  # the charts follow their boxes' new sizes
        b = await page.evaluate(BOXES)
        top = b["header"][1]
        assert top <= b["pads"][0] and b["pads"][1] <= height, (width, b)
        for box in b["plots"] + b["canvases"]:
            assert top <= box[0] and box[1] <= height and box[3] <= width, (width, b)
        assert all(box[1] - box[0] >= 80 for box in b["canvases"]), b  # charts, not slivers
    # a phone: the run history's wide rows scroll inside their card, never the page (which
    # took the E-STOP bar out of view), and each plot is a row of its own, none clipped
    row = {"id": 7, "started_at": "2026-12-07T10:00:00+00:00", "ended_at": None,
           "status": "completed", "iterations": 1234, "meta": {"object": {"name": "egg"}},
           "summary": {"message": "a long summary " * 6, "strokes": 3}}  # fmt: skip
    await page.route(RUN_LIST, lambda r: r.fulfill(json=[row], headers={"X-Total-Count": "1"}))
    await page.click("#runs-refresh")
    await expect(page.locator("#runs tbody")).to_contain_text("a long summary")
    await page.set_viewport_size({"width": 390, "height": 844})
    await page.wait_for_function(FITTED)
    wide = await page.evaluate("""() => ({
        page: document.documentElement.scrollWidth, view: window.innerWidth,
        table: document.querySelector('#runs').getBoundingClientRect().width,
        estop: document.querySelector('#estop').getBoundingClientRect().right,
        plots: [...document.querySelectorAll('.plot')].map((p) => p.getBoundingClientRect().right),
    })""")
    assert wide["table"] > wide["view"] >= wide["page"], wide  # the table is wider: it scrolls
    assert wide["estop"] <= wide["view"] and max(wide["plots"]) <= wide["view"], wide
    await page.unroute(RUN_LIST)
    await page.click("#runs-refresh")
    await page.set_viewport_size({"width": 1500, "height": 1200})
    # the parameters are in a drawer, closed until asked for
    k = page.locator("#params-form input[name=k]")
    assert await k.is_hidden()
    await page.click("#params-toggle")
    await expect(k).to_be_visible()
    # the keyboard lands in the drawer's first field (not at the end of the page), and back
    await expect(
        page.locator("#params-fields .field").first.locator("input, select")
    ).to_be_focused()
    await page.keyboard.press("Escape")
    await expect(k).to_be_hidden()
    await expect(page.locator("#params-toggle")).to_be_focused()
    await page.set_viewport_size({"width": 1500, "height": 1200})

    # an error toast clears once its problem is gone (the run history loads again) …
    await page.route(RUN_LIST, lambda r: r.fulfill(status=500, json={"error": "db busy"}))
    await page.click("#runs-refresh")
    toast = page.locator("#errors .toast", has_text="run history: db busy")
    await expect(toast).to_be_visible()
    await page.unroute(RUN_LIST)
    await page.click("#runs-refresh")
    await expect(toast).to_have_count(0)
    # … and expires by itself (the dashboard's clock moved on a minute, no waiting)
    await page.evaluate("window.sdh2debug.toast('something failed', {key: 'test'})")
    await expect(page.locator("#errors .toast")).to_have_count(1)
    await page.evaluate("window.sdh2debug.expireToasts(Date.now() + 60000)")
    await expect(page.locator("#errors .toast")).to_have_count(0)
    # the same error again with other details (another field): the toast shows the new ones
    details = await page.evaluate("""() => {
        window.sdh2debug.toast('bad parameters', {details: ['k = 0.5: too small']});
        const box = window.sdh2debug.toast('bad parameters', {details: ['cycles = 0: too few']});
        const got = [...box.querySelectorAll('li')].map((li) => li.textContent);
        box.remove();
        return got;
    }""")
    assert details == ["cycles = 0: too few"], details
    # a fault's message is not said twice when the service's words repeat the plain ones
    said = await page.evaluate("""async () => {
        const m = await import('/web/events.js');
        return [m.plainMessage('dropped: both contacts lost: the object is no longer held, or '
                               + 'both distal pads stopped reading it'),
                m.plainMessage('force_ceiling: F = 6.73 above 3 × Fd')];
    }""")
    assert said == ["both contacts were lost; the object is no longer held, or both distal pads "
                    "stopped reading it",
                    "the grip force went too high (F = 6.73 above 3 × Fd)"], said  # fmt: skip
    # a run's end says the range the object turned through, and where it ended (not the net
    # rotation at the end alone: a stroke there and back ends near where it began)
    said = await page.evaluate("""async () => {
        const m = await import('/web/events.js');
        const end = (recognition) => m.eventSentence(
            {kind: 'end', run_id: 3, detail: {status: 'completed', recognition}});
        return [end({object_class: 'ellipse', confidence: 0.9, rotation_deg: -0.31,
                     rotation_range_deg: 16.12}),
                end({object_class: 'ellipse', confidence: 0.9, rotation_deg: 0.3})];
    }""")
    assert said == ["Run 3 completed; recognised an ellipse (90 %), turned through 16.1° "
                    "(ends 0.3° from its start)",
                    "Run 3 completed; recognised an ellipse (90 %), ends 0.3° from its start",
                    ], said  # fmt: skip
    # an opening stopped says so once ("… stopped: stopped" before), and why when it knows
    said = await page.evaluate("""async () => {
        const m = await import('/web/events.js');
        const opened = (message) => m.eventSentence(
            {kind: 'opened', detail: {completed: false, message}});
        return [opened('stopped'), opened('joint_error: the fingers stopped 30.0° short')];
    }""")
    assert said[0] == "Opening the hand stopped", said
    assert said[1].startswith("Opening the hand stopped: ") and "30.0°" in said[1], said
    # the sketch's object: "released" when it fell as the run let go of it (its releasing
    # phase), "dropped" when it fell mid-run; fed with the sim's truth and a status each, in one
    # turn (no real message between), drawn at once
    fates = await page.evaluate(OBJECT_FATES)
    assert fates == ["held", "dropped", "dropped", "held", "released", "released"], fates
    # the browser's benign ResizeObserver note is no error
    await page.evaluate(
        "window.dispatchEvent(new ErrorEvent('error', {message: "
        "'ResizeObserver loop completed with undelivered notifications.'}))"
    )
    assert await page.locator("#errors .toast").count() == 0
    await page.evaluate("window.sdh2.lastError = null")

    # in simulation, press-and-hold on a pad's cell presses the pad there; letting go lifts it
    sel = "#pads canvas[data-matrix='3']"
    lit = f"(a) => ({COUNT_PIXELS_NOT})(a) > 0"
    await page.locator(sel).scroll_into_view_if_needed()  # the steps above scrolled the page
    box = await page.locator(sel).bounding_box()
    assert box is not None and not await page.evaluate(lit, [sel, PAD_ZERO_RGB])
    await page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    await page.mouse.down()
    await page.wait_for_function(lit, arg=[sel, PAD_ZERO_RGB], timeout=10_000)
    await page.mouse.up()
    await page.wait_for_function(f"(a) => !({lit})(a)", arg=[sel, PAD_ZERO_RGB], timeout=10_000)


# Strokes of the run the e-stop stops: the e-stop must come mid-run however long a loaded
# machine makes the page's steps before it (a 3-stroke egg run ends ≈ 60 s after its start).
ESTOP_RUN_CYCLES = 50


@contextlib.contextmanager
def _runs_of(service: LiveService, cycles: int) -> Iterator[None]:
    """The service's runs have ``cycles`` strokes; on leaving, its earlier number again (and
    a run still going is stopped: the module's other tests need an idle service)."""
    with service.sync_client() as client:
        before = client.params()["cycles"]
        client.patch_params({"cycles": cycles})
        try:
            yield
        finally:
            with contextlib.suppress(Conflict):  # (no run going: nothing to stop)
                client.stop_run()
            client.patch_params({"cycles": before})


async def test_run_plots_pads_viewer_estop_replay(service: LiveService, page: Any) -> None:
    with _runs_of(service, ESTOP_RUN_CYCLES):
        await _run_plots_pads_viewer_estop_replay(service, page)


async def _run_plots_pads_viewer_estop_replay(service: LiveService, page: Any) -> None:
    await page.select_option("#object-select", "egg")
    await page.wait_for_function("!document.querySelector('#start').disabled")
    # a changed parameter goes with Grasp & roll (one stroke more than the service's)
    cycles = page.locator(".field[data-field=cycles]")
    await page.click("#params-toggle")
    await cycles.locator("input").fill(str(ESTOP_RUN_CYCLES + 1))
    await page.keyboard.press("Escape")
    await expect(cycles).to_have_class(re.compile("dirty"))
    # an impatient double click starts one run: one request, no "already running" error
    starts: list[str] = []
    page.on("request", lambda r: starts.append(r.method) if r.url.endswith("/api/runs") else None)
    await page.dblclick("#start")
    # while a run is active the hand cannot be opened from here
    await expect(page.locator("#open-hand")).to_be_disabled(timeout=30_000)
    assert starts.count("POST") == 1, starts
    # the field sent is the run's parameter in force now: no longer marked changed
    await expect(cycles).not_to_have_class(re.compile("dirty"))
    await expect(cycles.locator("input")).to_have_value(str(ESTOP_RUN_CYCLES + 1))
    await page.wait_for_function(
        "window.sdh2.samples > 40 && window.sdh2.tactile > 40", timeout=RUN_TIMEOUT_MS
    )
    c = await counters(page)
    assert c["lastError"] is None, c["lastError"]
    assert await page.inner_text("#run-state") in ACTIVE
    assert int(await page.inner_text("#iteration")) > 0
    assert (await page.inner_text("#stroke")).endswith(f" of {ESTOP_RUN_CYCLES + 1}")
    assert "frames/s" in await page.inner_text("#bus-stats")

    # the plots have lines, the distal pads (matrices 1 and 5) show pressure, the sketch is drawn
    await page.wait_for_timeout(300)  # one animation frame at least
    for name in PLOTS:
        assert await page.evaluate(COUNT_COLOURED, f"#plot-{name} .uplot canvas") > 50, name
    for i in (1, 5):
        sel = f"#pads canvas[data-matrix='{i}']"
        assert await page.evaluate(COUNT_PIXELS_NOT, [sel, PAD_ZERO_RGB]) > 0, f"pad {i} blank"
    assert await page.evaluate(COUNT_COLOURED, "#sketch") > 100
    # the object readout follows the live samples (the recognition's estimate)
    await page.wait_for_function("Number(document.querySelector('#object-readout')"
                                 ".dataset.iteration) > 0")  # fmt: skip
    # the legends show the newest values without a hover
    legend = await page.inner_text("#plot-lambda .u-legend")
    assert re.search(r"Λ:?\s*\d", legend), legend

    # events read as sentences; the first reversal is marked on the plots' iteration axis
    await page.wait_for_selector("#events li.reversal", timeout=RUN_TIMEOUT_MS)
    texts = await page.locator("#events li").all_inner_texts()
    assert any(t.startswith("Grasped with F = ") for t in texts), texts
    assert any(t.startswith("Reversed") for t in texts), texts
    assert not any("{" in t or "=[" in t for t in texts), texts
    await page.wait_for_function(
        "Number(document.querySelector('#plot-sigma').dataset.reversals) >= 1"
    )
    # the run history's row of the running run counts its iterations along
    running = httpx.get(service.url + "/api/status").json()["run"]["id"]
    await page.wait_for_function(
        "(id) => Number(document.querySelector(`#runs tr[data-run-id='${id}'] td:nth-child(6)`)"
        "?.textContent) > 0",
        arg=running,
    )

    # a second page opened mid-run shows the run from its start: the earlier iterations and
    # events from the record, then the live ones
    await joined_mid_run(service, page)

    # e-stop mid-run: the run ends e-stopped, start is locked until the release
    await page.click("#estop")
    await page.wait_for_function(
        "document.querySelector('#run-state').textContent === 'e-stopped'"
        " && document.querySelector('#estop').classList.contains('latched')"
        " && document.querySelector('#start').disabled",
        timeout=30_000,
    )
    assert httpx.get(service.url + "/api/status").json()["estopped"] is True
    # the notice says what happened and what comes next
    run_id = httpx.get(service.url + "/api/status").json()["run"]["id"]
    notice = page.locator("#run-notice")
    await expect(notice).to_contain_text(f"Run {run_id} was e-stopped")
    await expect(notice).to_contain_text("Release the e-stop when it is safe, then open the hand.")
    await expect(page.locator("#notice-open-hand")).to_be_disabled()
    await screenshot(page, "estop-notice")
    await page.click("#estop-release")
    await page.wait_for_function("!document.querySelector('#start').disabled", timeout=15_000)
    assert httpx.get(service.url + "/api/status").json()["estopped"] is False
    await expect(notice).to_contain_text("Open the hand to let go of whatever it holds")
    await expect(page.locator("#notice-open-hand")).to_be_enabled()

    # the 3-D view (loaded when scrolled into sight): the iframe shows the viewer, which draws
    viewer = httpx.get(service.url + "/api/viewer").json()["url"]
    if viewer is None:
        assert await page.is_visible("#viewer-note")
    else:
        assert httpx.get(viewer, timeout=10.0).status_code == 200
        await page.locator("#viewer").scroll_into_view_if_needed()
        await page.wait_for_function(
            "document.querySelector('#viewer').src.startsWith(document.querySelector('#viewer')"
            ".dataset.url)", timeout=10_000,
        )  # fmt: skip
        frame = page.frame_locator("#viewer")
        await frame.locator("canvas").first.wait_for(state="attached", timeout=60_000)

    # the run is in the history: replay it, download its exports
    row = page.locator(f"#runs tbody tr[data-run-id='{run_id}']")
    await row.wait_for(timeout=15_000)
    samples = httpx.get(f"{service.url}/api/runs/{run_id}/samples?limit=10000").json()["samples"]
    async with page.expect_request(lambda r: r.url.endswith("/api/viewer/replay")) as fed:
        await row.locator("button.replay").click()
        await page.wait_for_function(f"window.sdh2.replaying === {run_id}", timeout=30_000)
    if viewer is not None:  # the 3-D view is told which recorded iteration to show
        req = await fed.value
        assert req.method == "PUT" and json.loads(req.post_data or "") == {
            "run_id": run_id, "iteration": samples[0]["iteration"]}  # fmt: skip
    assert await page.is_visible("#replay-banner")
    await page.wait_for_timeout(300)
    assert await page.evaluate(COUNT_COLOURED, "#plot-lambda .uplot canvas") > 50
    # the run's reversals are marked on every plot
    run = httpx.get(f"{service.url}/api/runs/{run_id}").json()
    reversals = [e for e in run["events"] if e["kind"] == "reversal"]
    assert reversals
    for name in PLOTS:
        marks = await page.get_attribute(f"#plot-{name}", "data-reversals")
        assert marks == str(len(reversals)), name
    # one scrubber: plots (cursor and legend), pads and sketch show the same iteration
    i = len(samples) // 2
    it = samples[i]["iteration"]
    seek = (
        f"(() => {{ const s = document.querySelector('#replay-scrubber'); s.value = '{i}';"
        " s.dispatchEvent(new Event('input')); })()"
    )
    await page.evaluate(seek)
    shown = await page.evaluate(SHOWN)
    assert shown["pads"] == shown["sketch"] == shown["readout"] == str(it), shown
    assert shown["plots"] == [str(it)] * len(PLOTS), shown
    # … and the readout and the sketch that iteration's recognition, its outline as recorded
    assert shown["readoutClass"] == (samples[i]["object_class"] or ""), shown
    est = httpx.get(f"{service.url}/api/runs/{run_id}/samples",
                    params={"offset": i, "limit": 1, "outline": "true"}).json()  # fmt: skip
    drawn = "document.querySelector('#sketch').dataset.estimatePoints"  # once the page has it
    n_est = len(est["samples"][0]["estimate_outline"])
    await page.wait_for_function(f"{drawn} === '{n_est}'", timeout=10_000)
    # in simulation the sketch draws the object where the recording has it at that iteration
    truth = httpx.get(f"{service.url}/api/runs/{run_id}/truth?from={it}&limit=1").json()["truth"]
    assert [float(v) for v in shown["objectPose"].split(",")] == [
        truth[0]["y"], truth[0]["z"], truth[0]["psi"]], shown  # fmt: skip
    assert shown["cursors"] == [i] * len(PLOTS) and shown["index"] == i, shown
    assert shown["at"].startswith(f"iteration {it} · "), shown
    assert "no data" not in shown["padInfo"] and "max 0 · Σ 0" != shown["padInfo"], shown
    legend = await page.inner_text("#plot-lambda .u-legend")  # the legend at the scrubber
    assert re.search(rf"it:?\s*{it}(?!\d)", legend), legend
    # play at 10×: everything moves on together
    await page.select_option("#replay-speed", "10")
    await page.click("#replay-play")
    await page.wait_for_function(f"window.sdh2.replayIndex > {i + 5}", timeout=30_000)
    # pause with the button unless the play has reached the end and paused itself meanwhile
    # (a loaded machine): checked and clicked in one turn of the page's event loop, since a
    # click on a paused replay at its end plays it again from the start
    await page.evaluate(PAUSE)
    shown = await page.evaluate(SHOWN)
    assert shown["pads"] == shown["sketch"] == shown["plots"][0] != str(it), shown
    assert shown["cursors"] == [shown["index"]] * len(PLOTS), shown
    # the keys step it (with nothing focused): one iteration, ten with shift — from the middle
    # again (the play may have reached the end on a loaded machine)
    await page.evaluate(seek)
    await page.evaluate("document.activeElement.blur()")
    await page.keyboard.press("ArrowRight")
    await page.keyboard.press("Shift+ArrowLeft")
    assert (await page.evaluate(SHOWN))["index"] == i - 9
    # … and so do they from the play button (focused once clicked) and the scrubber
    await page.focus("#replay-play")
    await page.keyboard.press("Shift+ArrowRight")
    assert (await page.evaluate(SHOWN))["index"] == i + 1
    await page.focus("#replay-scrubber")
    await page.keyboard.press("Shift+ArrowLeft")
    await page.keyboard.press("ArrowLeft")
    assert (await page.evaluate(SHOWN))["index"] == i - 10
    await screenshot(page, "replay")
    for fmt in ("csv", "mcap"):
        href = await row.locator(f"a.export-{fmt}").get_attribute("href")
        r = httpx.get(service.url + href, timeout=30.0)
        assert r.status_code == 200 and r.content, fmt
    if viewer is not None:  # the 3-D view goes live again with the dashboard
        async with page.expect_request(lambda r: r.method == "DELETE") as ended:
            await page.click("#back-to-live")
        assert (await ended.value).url.endswith("/api/viewer/replay")
    else:
        await page.click("#back-to-live")
    assert await page.is_hidden("#replay-banner")
    assert await page.get_attribute("#pads", "data-iteration") is None
    # the replay's cursors are parked off the plots: live, nothing holds an old iteration
    lefts = await page.evaluate("window.sdh2debug.plots.charts.map(c => c.cursor.left)")
    assert all(left < 0 for left in lefts), lefts
    assert (await counters(page))["lastError"] is None


async def joined_mid_run(service: LiveService, page: Any) -> None:
    """A page opened on ``service`` while its run rolls plots that run from its first iteration,
    with no gap up to the live samples, lists the grasp and the reversals before it opened (once
    each), and marks those reversals on its plots."""
    context = await page.context.browser.new_context(viewport={"width": 1500, "height": 1200})
    try:
        late = await context.new_page()
        errors: list[str] = []
        late.on("pageerror", lambda e: errors.append(str(e)))
        await late.goto(page.url)
        try:
            await late.wait_for_function(
                "window.sdh2.backfilled !== null || window.sdh2.lastError !== null",
                timeout=30_000,
            )
        except playwright_api.TimeoutError:
            raise AssertionError(f"no backfill: {await counters(late)}") from None
        got = await late.evaluate("""() => {
          const live = window.sdh2debug.plots.live;
          return {backfilled: window.sdh2.backfilled, lastError: window.sdh2.lastError,
                  iterations: live.samples.map(s => s.iteration),
                  reversals: live.markers.filter(m => m.kind === 'reversal').length,
                  events: [...document.querySelectorAll('#events li')].map(li => li.textContent),
                  older: document.querySelectorAll('#events li[data-backfilled]').length};
        }""")
        assert got["lastError"] is None, got["lastError"]
        its = got["iterations"]
        run_id = httpx.get(service.url + "/api/status").json()["run"]["id"]
        first = httpx.get(f"{service.url}/api/runs/{run_id}/samples?limit=1").json()["samples"]
        assert got["backfilled"]["samples"] > 0 and its[0] == first[0]["iteration"], its[:5]
        assert its == list(range(its[0], its[0] + len(its))), "a gap or a repeat in the plots"
        assert got["older"] == got["backfilled"]["events"] > 0
        grasped = [t for t in got["events"] if t.startswith("Grasped with F = ")]
        assert len(grasped) == 1, got["events"]
        assert got["reversals"] >= 1
        # ψ at the grasp, which it did not see live, from the truth recorded with the first
        # sample: its readout says how far the object truly turned, as the first page's does
        truth = httpx.get(f"{service.url}/api/runs/{run_id}/truth?limit=1").json()["truth"]
        await late.wait_for_function("window.sdh2debug.liveTurn.psi0 !== null")
        psi0 = await late.evaluate("window.sdh2debug.liveTurn.psi0")
        assert psi0 == truth[0]["psi"], (psi0, truth[0])
        await late.wait_for_function(
            "document.querySelector('#object-readout').textContent.includes('(true ')"
        )
        assert errors == [], errors
    finally:
        await context.close()


async def test_a_refresh_during_a_load_fetches_the_history_again(
    service: LiveService, page: Any
) -> None:
    """A click on Refresh while an earlier load of the run history is still out (a run's
    start or end starts one) is answered by a fresh request, not by that earlier load's
    answer: the earlier one fails, the click's succeeds, and no error stays."""
    held: list[Any] = []
    asked = asyncio.Event()

    async def hold(route: Any) -> None:
        """The first request waits (it is the earlier load); later ones go to the server."""
        if held:
            await route.continue_()
        else:
            held.append(route)
            asked.set()

    await page.route(RUN_LIST, hold)
    await page.evaluate("document.querySelector('#runs-refresh').click()")  # the earlier load
    await asyncio.wait_for(asked.wait(), 10)
    await page.click("#runs-refresh")  # while the earlier one is out
    # the earlier load fails; then a fresh request goes out and is answered
    async with page.expect_response(lambda r: bool(RUN_LIST.search(r.url)) and r.ok):
        await held[0].fulfill(status=500, json={"error": "db busy"})
    await expect(page.locator("#errors .toast", has_text="run history")).to_have_count(0)
    await expect(page.locator("#runs tbody tr").first).to_be_visible()
    await page.unroute(RUN_LIST)


async def test_a_run_is_deleted_once_the_person_confirms_and_older_runs_are_listed(
    service: LiveService, page: Any
) -> None:
    """Delete asks first (a dismissed question deletes nothing); the run history lists the
    newest 50 and, while there are older ones, offers 50 more."""
    store = RunStore(service.db_path)  # a finished run of its own, whatever ran before
    try:
        oldest = store.create_run({"object": {"name": "egg"}})
        store.finish_run(oldest, "completed", {"status": "completed", "iterations": 0})
    finally:
        store.close()
    # (clicks as events: a click of Playwright's scrolls the history into sight, which loads
    # the 3-D view's iframe and keeps the page busy for seconds)
    await page.locator("#runs-refresh").dispatch_event("click")
    row = page.locator(f"#runs tbody tr[data-run-id='{oldest}']")
    asked: list[str] = []

    async def dismiss(dialog: Any) -> None:
        asked.append(dialog.message)
        await dialog.dismiss()

    async def accept(dialog: Any) -> None:
        await dialog.accept()

    page.once("dialog", dismiss)
    await row.locator("button.delete").dispatch_event("click")
    assert f"Delete run {oldest} (" in asked[0] and "cannot be undone" in asked[0]
    assert httpx.get(f"{service.url}/api/runs/{oldest}").status_code == 200
    page.once("dialog", accept)
    await row.locator("button.delete").dispatch_event("click")
    await expect(row).to_have_count(0)
    assert httpx.get(f"{service.url}/api/runs/{oldest}").status_code == 404
    assert (await counters(page))["lastError"] is None

    # 51 runs where 50 are listed: "Older runs" is offered, and asks for 50 more
    many = [{"id": i, "started_at": "2026-12-01T09:00:00.000+0000", "ended_at": None,
             "status": "completed", "iterations": 0, "meta": {}, "summary": None}
            for i in range(1000, 949, -1)]  # fmt: skip
    # a run that never rolled says no rotation; one that rolled, how far the object turned
    many[0].update(status="faulted", summary={"message": "no_contact",
                                              "truth": {"rotation_range_deg": 0.0}})  # fmt: skip
    many[1].update(iterations=120, summary={"truth": {"rotation_range_deg": 16.14}})
    await page.route(re.compile(r"/api/runs\?limit=51$"), lambda r: r.fulfill(json=many))
    await page.locator("#runs-refresh").dispatch_event("click")
    await expect(page.locator("#runs tbody tr")).to_have_count(50)
    summary = "#runs tbody tr[data-run-id='{}'] td:nth-child(8)"
    await expect(page.locator(summary.format(1000))).to_have_text("no_contact")
    await expect(page.locator(summary.format(999))).to_have_text("true rot 16.1°")
    async with page.expect_request(re.compile(r"/api/runs\?limit=101$")):
        await page.locator("#runs-older").dispatch_event("click")
    await expect(page.locator("#runs-older")).to_be_hidden()  # the service has fewer
    await page.unroute(re.compile(r"/api/runs\?limit=51$"))


async def test_a_long_run_replays_at_one_iteration_in_every_k(
    service: LiveService, page: Any
) -> None:
    """A run too long to load whole (here 20 500 iterations against the page's 10 000) is
    replayed at one iteration in 3, the same ones of its samples, frames and truth: the banner
    says so, the scrubber spans the run and each shown iteration has its pads and object."""
    cfg = load_config(use_env=False)
    n = sum(r * c for r, c in matrix_shapes(cfg.tactile, cfg.axes))
    total = 20_500
    store = RunStore(service.db_path)
    try:
        run_id = store.create_run({"object": {"name": "disc"}})
        store.set_outline(run_id, "disc", 20.0, [(10.0, 0.0), (0.0, 10.0), (-10.0, 0.0)])
        rec = Recorder(store.path, run_id)
        for i in range(1, total + 1):
            s = replay_sample(i)
            rec.sample(s)
            rec.frame(s.t, i, i, replay_texels(i, n))
            rec.truth(i, s.t, (30.0, 110.0, 1e-4 * i), True, False, False, 0)
        rec.close()
        store.finish_run(run_id, "completed", {"status": "completed"})
    finally:
        store.close()
    asked: list[str] = []
    page.on("request", lambda r: asked.append(r.url) if f"/api/runs/{run_id}/" in r.url else None)
    await page.locator("#runs-refresh").dispatch_event("click")
    row = page.locator(f"#runs tbody tr[data-run-id='{run_id}']")
    # the list as it is now: one the page fetched while the run was being written has its row
    # with the status and iterations of then, and its replay would work out its step from those
    await expect(row.locator("td").nth(3)).to_have_text("completed")
    await row.locator("button.replay").dispatch_event("click")
    await page.wait_for_function(f"window.sdh2.replaying === {run_id}", timeout=60_000)
    # the legends show the scrubber's iteration from the start (the first: φ2 = 10 + 1)
    await legends_at(page, [1, 11])
    assert await page.get_attribute("#replay-banner", "data-every") == "3"
    text = await page.inner_text("#replay-text")
    assert f"{total} iterations (every 3rd shown)" in text, text
    shown = (total - 1) // 3 + 1  # iterations 1, 4, …, 20 497
    assert await page.get_attribute("#replay-scrubber", "max") == str(shown - 1)
    reads = [u for u in asked if re.search(r"/(samples|frames|truth)\?", u)]
    assert reads and all("every=3" in u for u in reads), reads  # nothing read whole
    last = 1 + 3 * (shown - 1)
    await page.evaluate(
        f"(() => {{ const s = document.querySelector('#replay-scrubber'); s.value = '{shown - 1}';"
        " s.dispatchEvent(new Event('input')); })()"
    )
    got = await page.evaluate(SHOWN)
    assert got["pads"] == got["sketch"] == got["readout"] == str(last), got
    await legends_at(page, [last, 10 + last])  # the last too
    assert got["plots"] == [str(last)] * len(PLOTS) and got["at"].startswith(f"iteration {last} ")
    assert "no data" not in got["padInfo"], got  # the iteration's own frame
    y, z, psi = (float(v) for v in got["objectPose"].split(","))
    assert (y, z) == (30.0, 110.0) and psi == pytest.approx(1e-4 * last)  # and its truth
    await page.click("#back-to-live")


# The joints plot's legend: each series' label and value.
JOINTS_LEGEND = """() => Object.fromEntries([...document.querySelectorAll(
  '#plot-joints .u-legend .u-series')].map((s) => [s.querySelector('.u-label').textContent,
                                                  s.querySelector('.u-value').textContent]))"""


async def legends_at(page: Any, values: list[int]) -> None:
    """The joints plot's legend comes to show iteration and φ2 ``values`` (as uPlot writes a
    number); a value the sample has not (its φ2d…φ5d: the test's samples have no targets) says
    so with uPlot's "--", not blank."""
    want = await page.evaluate("(vs) => vs.map((v) => uPlot.fmtNum(v))", values)
    shows = f"(w) => {{ const g = ({JOINTS_LEGEND})(); return g.it === w[0] && g['φ2'] === w[1]; }}"
    try:
        await page.wait_for_function(shows, arg=want)
    except playwright_api.TimeoutError:
        raise AssertionError(f"legend {await page.evaluate(JOINTS_LEGEND)}, not {want}") from None
    got = await page.evaluate(JOINTS_LEGEND)
    assert [got[f"φ{i}d"] for i in range(2, 6)] == ["--"] * 4, got


# The toasts shown, and whether one overlaps the open parameter drawer (its Apply and Reset
# buttons, scrolled into its sight, are at the bottom of its box on a small screen).
COVERED = """() => {
  document.querySelector('#params-apply').scrollIntoView({block: 'nearest'});
  const box = (e) => e.getBoundingClientRect();
  const meet = (a, b) =>
    a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom;
  const toasts = [...document.querySelectorAll('#errors .toast')].map(box);
  const drawer = ['#params-drawer', '#params-apply', '#params-reset'].map(
    (s) => box(document.querySelector(s)));
  return {toasts: toasts.length, covered: toasts.some((t) => drawer.some((b) => meet(t, b)))};
}"""


async def test_bad_parameter_shows_the_422_next_to_the_field(
    service: LiveService, page: Any
) -> None:
    before = httpx.get(service.url + "/api/params").json()
    # what the server says about k = 0.5 (a rejected patch changes nothing)
    r = httpx.patch(service.url + "/api/params", json={"k": 0.5}, headers=service.headers())
    assert r.status_code == 422
    body = r.json()
    expected = next(d for d in body["details"] if d.startswith("k"))

    await page.click("#params-toggle")  # the parameters' drawer
    await page.fill("#params-form input[name=k]", "0.5")
    # the client-side range check speaks at once …
    await page.wait_for_function(
        "document.querySelector('[data-error-for=k]').textContent.includes('allowed')"
    )
    # … and the server's own message replaces it after Apply
    await page.click("#params-apply")
    err = page.locator("#params-form [data-error-for=k]")
    await page.wait_for_function(
        "([sel, text]) => document.querySelector(sel).textContent === text",
        arg=["#params-form [data-error-for=k]", expected],
        timeout=10_000,
    )
    assert await err.is_visible()
    assert body["error"] in await page.inner_text("#errors")
    assert body["error"] in (await counters(page))["lastError"]
    # the field says it is wrong, and why, to a screen reader too
    k = page.locator("#params-form input[name=k]")
    await expect(k).to_have_attribute("aria-invalid", "true")
    described = (await k.get_attribute("aria-describedby") or "").split()
    assert "param-k-error" in described, described
    await expect(page.locator("#param-k-error")).to_have_text(expected)
    await expect(k).to_be_focused()  # the keyboard on it (the drawer was open already)
    # the error's toast does not cover the open drawer's buttons (on a laptop's screen, where
    # the drawer's buttons reach down to the toasts' corner)
    await page.set_viewport_size({"width": 1024, "height": 768})
    boxes = await page.evaluate(COVERED)
    await page.set_viewport_size({"width": 1500, "height": 1200})
    assert boxes["toasts"] and not boxes["covered"], boxes
    assert httpx.get(service.url + "/api/params").json() == before

    # a valid value is applied and clears the message
    await page.fill("#params-form input[name=k]", str(before["k"] + 1))
    await page.click("#params-apply")
    await page.wait_for_function(
        "document.querySelector('[data-error-for=k]').textContent === ''", timeout=10_000
    )
    await expect(k).not_to_have_attribute("aria-invalid", "true")
    assert httpx.get(service.url + "/api/params").json()["k"] == before["k"] + 1
    r = httpx.patch(service.url + "/api/params", json={"k": before["k"]}, headers=service.headers())
    assert r.status_code == 200


async def test_token_field_when_the_service_needs_one(tmp_path: Path) -> None:
    token = "dashboard-test-token"
    svc = start_service(tmp_path, viewer=False, token=token)
    lie = StatusLie()
    try:
        async with dashboard(svc, lie=lie) as page:
            # stopping needs no token: E-STOP with the token field empty sends none (as JSON);
            # the service's answer is made to say what a silent joint line and a locked run
            # database make it say (the stop itself is real)
            lie.on = True
            await page.route("**/api/estop", unconfirmed_estop)
            async with page.expect_response(lambda r: r.url.endswith("/api/estop")) as answer:
                await page.click("#estop")
            resp = await answer.value
            assert resp.request.method == "POST" and resp.request.post_data == "{}"
            assert "authorization" not in resp.request.headers
            assert resp.status == 200
            await page.unroute("**/api/estop")
            estop = page.locator("#estop")
            await expect(estop).to_have_class(re.compile("latched"))
            await expect(page.locator("#open-hand")).to_be_disabled()
            await expect(page.locator("#open-hand-hint")).to_contain_text(
                "release the e-stop first"
            )
            await estop_shown_and_unconfirmed(svc, page, lie)
            r = httpx.post(svc.url + "/api/estop/release", json={}, headers=svc.headers())
            assert r.status_code == 200
            await expect(page.locator("#estop-release")).to_be_disabled()
            await expect(page.locator("#estop-banner")).to_be_hidden()
            await expect(estop).to_have_text("E-STOP")
            await expect(estop).to_have_attribute("aria-pressed", "false")
            await expect(page.locator("#estop-latch")).to_be_hidden()
            # the status says a token is needed: the field shows; without it a change is refused
            assert await page.is_visible("#token-field")
            before = httpx.get(svc.url + "/api/params").json()
            await page.click("#params-toggle")  # the parameters' drawer
            await page.fill("#params-form input[name=lambda_gain]", str(before["lambda_gain"] + 1))
            await page.click("#params-apply")
            await page.wait_for_function("window.sdh2.lastError !== null", timeout=10_000)
            assert "token" in (await counters(page))["lastError"]
            assert "token" in await page.inner_text("#errors")
            # with the token typed in (kept in localStorage) the same change goes through
            await page.fill("#token", token)
            await page.dispatch_event("#token", "change")
            await page.click("#params-apply")
            await page.wait_for_function(
                "!document.querySelector('.field[data-field=lambda_gain]')"
                ".classList.contains('dirty')",
                timeout=10_000,
            )
            assert httpx.get(svc.url + "/api/params").json()["lambda_gain"] == (
                before["lambda_gain"] + 1
            )
            stored = await page.evaluate("localStorage.getItem('sdh2svc.token')")
            assert stored == token
    finally:
        assert svc.stop() == 0, "".join(svc.log)


UNCONFIRMED = (
    "the hand has not confirmed the stop yet (the joint line does not answer); its power-off "
    "is sent again as soon as the line answers; the latch is still being written to the run "
    "database (runs.sqlite: another program holds it locked)"
)


# How the page shows every wall-clock time: local, ISO-like.
WALL_TIME = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"


async def local_time(page: Any, iso: str) -> str:
    """The API's time ``iso`` in the browser's local time, ``YYYY-MM-DD HH:MM:SS``."""
    parts = await page.evaluate(
        "(s) => { const d = new Date(s.replace(/\\+0000$/, 'Z'));"
        " return [d.getFullYear(), d.getMonth() + 1, d.getDate(), d.getHours(), d.getMinutes(),"
        " d.getSeconds()]; }",
        iso,
    )
    y, mo, d, h, mi, sec = parts
    return f"{y:04d}-{mo:02d}-{d:02d} {h:02d}:{mi:02d}:{sec:02d}"


async def unconfirmed_estop(route: Any) -> None:
    """POST /api/estop goes to the service; its answer says the hand has not confirmed it and
    the disk has not taken it yet."""
    real = await route.fetch()
    body = {**await real.json(), "hand_reached": False, "recorded": False, "detail": UNCONFIRMED}
    await route.fulfill(response=real, json=body)


# The last status the page got with one value changed (`path`: its keys), fed as a status
# message; what the e-stop banner then shows (in the same turn: no real status comes between).
FEED_STATUS = """([path, value]) => {
  const st = structuredClone(window.sdh2debug.status());
  let at = st;
  for (const key of path.slice(0, -1)) at = at[key];
  at[path[path.length - 1]] = value;
  window.sdh2debug.onMessage({type: 'status', status: st});
  const text = (sel) => {
    const e = document.querySelector(sel);
    return e.hidden ? null : e.textContent;
  };
  return {banner: !document.querySelector('#estop-banner').hidden, hand: text('#estop-hand'),
          disk: text('#estop-disk'), latch: text('#estop-latch')};
}"""


async def estop_shown_and_unconfirmed(svc: LiveService, page: Any, lie: StatusLie) -> None:
    """(In the token test's page, the e-stop latched by a click the hand did not confirm, and
    statuses saying so.) The latch is in the button's text and state, its tooltip says since
    when and why; what the hand and the disk have not confirmed is in a banner until a status
    shows it done."""
    estop = page.locator("#estop")
    await expect(estop).to_have_text("E-STOP (latched)")
    await expect(estop).to_have_attribute("aria-pressed", "true")
    reason = httpx.get(svc.url + "/api/status").json()["estop"]["reason"]
    await expect(estop).to_have_attribute(
        "title", re.compile(rf"latched since .*\({re.escape(reason)}\)")
    )
    banner = page.locator("#estop-banner")
    await expect(banner).to_be_visible()
    await expect(page.locator("#estop-hand")).to_contain_text(
        "The hand has not confirmed the e-stop"
    )
    await expect(page.locator("#estop-hand")).to_contain_text(
        "use the hand's own emergency-stop switch"
    )
    await expect(page.locator("#estop-detail")).to_contain_text(UNCONFIRMED)
    # the status says the latch is on disk: that note goes; the hand's stays (the status says
    # it has not confirmed the power-off)
    await expect(page.locator("#estop-disk")).to_be_hidden()
    seen = (await counters(page))["statusMsgs"]
    await page.wait_for_function(f"window.sdh2.statusMsgs > {seen}")
    await expect(page.locator("#estop-hand")).to_be_visible()
    # the service's word, not the click's answer: a status saying the hand confirmed it clears
    # the note, one saying it has not shows it (as on a page that never sent the e-stop)
    # … and the line next to the E-STOP (always in sight, not only in a tooltip) says since
    # when, why, and whether the hand confirmed the power-off
    since = httpx.get(svc.url + "/api/status").json()["estop"]["since"]
    at = await local_time(page, since)
    shown = await page.evaluate(FEED_STATUS, [["estop", "hand_reached"], True])
    assert shown["hand"] is None, shown
    assert shown["latch"] == f"latched {at} — {reason} · hand confirmed", shown
    shown = await page.evaluate(FEED_STATUS, [["estop", "hand_reached"], False])
    assert shown["banner"] and "has not confirmed" in (shown["hand"] or ""), shown
    assert shown["latch"] == f"latched {at} — {reason} · hand NOT confirmed yet", shown
    # a latch another program wrote (`sdh2svc estop --latch`) shows the same way
    shown = await page.evaluate(FEED_STATUS, [["estop", "reason"], "latched from the command line"])
    assert shown["latch"].startswith(f"latched {at} — latched from the command line · "), shown
    # a status saying the latch is not (yet) on disk shows a note saying so, and what it means
    for recorded, says, short in (("pending", "not on disk yet", "not on disk yet"),
                                  ("no", "did not take it", "not on disk")):  # fmt: skip
        shown = await page.evaluate(FEED_STATUS, [["estop", "recorded"], recorded])
        assert shown["banner"] and says in (shown["disk"] or ""), shown
        assert "a restart of the service would not keep it" in shown["disk"], shown
        assert shown["latch"].endswith(f" · hand NOT confirmed yet · {short}"), shown
    # the service says the hand confirmed it (the owed power-off went out): the banner goes
    lie.on = False
    await expect(page.locator("#estop-hand")).to_be_hidden()
    await expect(banner).to_be_hidden()


# A custom object (no preset), as `serve --object-file` or a lab script's PUT gives it.
LAB_BLOCK = {
    "kind": "box", "name": "lab-block", "width_mm": 40, "height_mm": 30, "corner_radius_mm": 2,
    "depth_mm": 30, "material": {"mass_g": 40, "friction": 0.6, "stiffness_n_per_mm3": 3.0},
}  # fmt: skip


# The hand's own events of an Open hand that an e-stop halts part-way (as the service sends
# them), fed in one turn; then the opening's toasts and the notice.
OPENING_ESTOPPED = """() => {
  const ev = (kind, detail) => window.sdh2debug.onMessage(
    {type: 'event', run_id: null, t: null, iteration: null, kind, detail});
  ev('open', {});
  ev('opened', {completed: false, message: 'stopped'});
  ev('estop', {});
  return {toasts: document.querySelectorAll('#errors .toast[data-key="opening"]').length,
          notice: window.sdh2.notice};
}"""


async def test_a_faulted_run_says_what_happened_and_offers_open_hand(tmp_path: Path) -> None:
    # a grasp that gives up 2° in, before the fingers reach the object: the run faults with
    # no_contact and the fingers hold still; the object is a custom one, from a file
    block = tmp_path / "block.json"
    block.write_text(json.dumps(LAB_BLOCK))
    extra = ("--set", "run.grasp_max_close_deg=-28", "--object-file", str(block))
    svc = start_service(tmp_path, viewer=False, extra=extra)
    try:
        async with dashboard(svc) as page:
            notice = page.locator("#run-notice")
            assert await notice.is_hidden()
            await expect(page.locator("#open-hand")).to_be_enabled()  # idle, no e-stop
            # the custom object is the one selected; Grasp & roll sends no preset's name for
            # it (the API takes the current object): the run starts
            select = page.locator("#object-select")
            await expect(select.locator("option:checked")).to_have_text("lab-block (custom)")
            async with page.expect_response(lambda r: r.url.endswith("/api/runs")) as started:
                await page.click("#start")
            resp = await started.value
            assert resp.status == 201, await resp.text()
            assert "object" not in json.loads(resp.request.post_data or ""), resp.request.post_data
            await expect(notice).to_be_visible(timeout=RUN_TIMEOUT_MS)
            st = httpx.get(svc.url + "/api/status").json()
            run_id = st["run"]["id"]
            assert st["object"]["name"] == "lab-block", st["object"]
            await expect(notice).to_contain_text(f"Run {run_id} faulted:")
            await expect(notice).to_contain_text("the grasp found nothing between the fingertips")
            await expect(notice).to_contain_text(
                "The fingers are holding still where the grasp gave up."
            )
            open_in_notice = page.locator("#notice-open-hand")
            await expect(open_in_notice).to_be_enabled(timeout=15_000)  # the run is over
            await expect(page.locator("#open-hand")).to_be_enabled()
            assert httpx.get(svc.url + "/api/status").json()["last_run"]["status"] == "faulted"
            await screenshot(page, "fault-notice")

            # another client changes the object: the selector follows, to a preset and back
            for body, shown in (
                ({"name": "egg"}, "egg"),
                ({"spec": LAB_BLOCK}, "lab-block (custom)"),
            ):
                assert httpx.put(svc.url + "/api/sim/object", json=body).status_code == 200
                await expect(select.locator("option:checked")).to_have_text(shown)
                await expect(select.locator("option", has_text="(custom)")).to_have_count(
                    1 if "custom" in shown else 0
                )

            # Open hand sends POST /api/hand/open (JSON); a refusal is shown in the notice
            route = "**/api/hand/open"
            refusal = {"error": "run 9 is running: stop it first", "details": []}
            await page.route(route, lambda r: r.fulfill(status=409, json=refusal))
            async with page.expect_request(lambda r: r.url.endswith("/api/hand/open")) as sent:
                await open_in_notice.click()
            req = await sent.value
            assert req.method == "POST" and req.post_data == "{}"
            assert req.headers["content-type"] == "application/json"
            await expect(page.locator("#run-notice-error")).to_have_text(
                f"Open hand was refused: {refusal['error']}"
            )
            assert refusal["error"] in (await counters(page))["lastError"]
            await expect(open_in_notice).to_be_enabled()  # may be tried again
            await page.evaluate("window.sdh2.lastError = null")

            # accepted (202): the error goes; the `opened` event says the hand is open
            await page.unroute(route)
            await page.route(route, lambda r: r.fulfill(status=202, json={"opening": True}))
            async with page.expect_request(lambda r: r.url.endswith("/api/hand/open")):
                await page.click("#open-hand")
            await expect(page.locator("#run-notice-error")).to_be_hidden()
            # while the status says the hand is opening, Open hand waits
            # (Stop can halt the opening: POST /api/runs/stop holds the fingers where they are)
            opening = await page.evaluate("""() => {
                const st = structuredClone(window.sdh2debug.status());
                st.hand.opening = true;
                window.sdh2debug.onMessage({type: 'status', status: st});
                const stop = document.querySelector('#stop');
                return [document.querySelector('#open-hand').disabled,
                        document.querySelector('#start').disabled,
                        document.querySelector('#open-hand-hint').textContent,
                        stop.disabled, stop.title];
            }""")
            assert opening[:4] == [True, True, "opening…", False], opening
            assert "halt the opening" in opening[4], opening
            # an opening stopped part-way: the hand is not open, Open hand is offered still
            opened = (
                "(detail) => window.sdh2debug.onMessage({type: 'event', run_id: null, t: null,"
                " iteration: null, kind: 'opened', detail})"
            )
            await page.evaluate(opened, {"completed": False, "message": "stopped"})
            await expect(notice).to_contain_text("Opening the hand was stopped part-way")
            await expect(notice).to_contain_text("the object may still be held")
            await expect(notice).not_to_have_class(re.compile("resolved"))
            await expect(open_in_notice).to_be_visible()
            await page.evaluate(opened, {"completed": True})
            await expect(notice).to_contain_text("The hand is open now.")
            await expect(notice).to_have_class(re.compile("resolved"))
            await expect(open_in_notice).to_be_hidden()
            # an opening e-stopped part-way (its `opened` says stopped, the hand's `estop`
            # follows) is a notice of its own, not a line of the last run's; the opening's
            # toast goes with the opening's end
            await expect(page.locator("#open-hand")).to_be_enabled()
            await page.click("#open-hand")
            toast = page.locator("#errors .toast", has_text="Opening the hand…")
            await expect(toast).to_be_visible()
            said = await page.evaluate(OPENING_ESTOPPED)
            assert said["toasts"] == 0, said
            assert said["notice"].startswith("Opening the hand was e-stopped:"), said
            assert "Run " not in said["notice"] and "(stopped)" not in said["notice"], said
            await expect(notice).not_to_have_class(re.compile("resolved"))
            await expect(open_in_notice).to_be_visible()
            await page.evaluate(opened, {"completed": True})  # opened again: the hand is open
            await expect(notice).to_contain_text("The hand is open now.")
            await page.unroute(route)

            # with the e-stop latched Open hand waits for the release, and says so
            assert httpx.post(svc.url + "/api/estop", json={}).status_code == 200
            await expect(page.locator("#open-hand")).to_be_disabled()
            await expect(page.locator("#open-hand-hint")).to_have_text(
                "release the e-stop first to open the hand"
            )
            assert httpx.post(svc.url + "/api/estop/release", json={}).status_code == 200
            await expect(page.locator("#open-hand")).to_be_enabled()
            await page.click("#notice-dismiss")
            await expect(notice).to_be_hidden()

            # after a restart the status names the run the service was killed during
            message = "the service stopped during this run (killed or crashed)"
            await page.evaluate(
                """(message) => {
                    const st = structuredClone(window.sdh2debug.status());
                    st.last_run = {id: 99, status: 'interrupted', message};
                    window.sdh2debug.onMessage({type: 'status', status: st});
                }""",
                message,
            )
            await expect(notice).to_contain_text("Run 99 was interrupted:")
            await expect(notice).to_contain_text("the object may still be held")
            await expect(open_in_notice).to_be_visible()
            await expect(open_in_notice).to_be_enabled()
            # a newer run that ended well: the older run's notice is history, also while the
            # status's last_run still names the older run (the newer one's end not yet written)
            inject = """(change) => {
                const st = structuredClone(window.sdh2debug.status());
                Object.assign(st, change);
                window.sdh2debug.onMessage({type: 'status', status: st});
            }"""
            done = {"id": 100, "state": "done", "stroke": 1, "strokes_total": 1,
                    "iteration": 40, "status": "completed", "message": ""}  # fmt: skip
            await page.evaluate(inject, {"run": done})
            await expect(notice).to_be_hidden()
            ended = {"id": 100, "status": "completed", "message": ""}
            await page.evaluate(inject, {"run": None, "last_run": ended})
            await expect(notice).to_be_hidden()
            # a run the service's shutdown stopped says so (not "on request")
            stopped = {"id": 101, "status": "stopped", "message": "as the service shut down"}
            await page.evaluate(inject, {"run": None, "last_run": stopped})
            await expect(notice).to_contain_text(
                "Run 101 was stopped as the service shut down; the fingers released the object."
            )
            assert (await counters(page))["lastError"] is None
    finally:
        assert svc.stop() == 0, "".join(svc.log)


async def test_a_dead_service_greys_out_the_dashboard_until_it_is_back(tmp_path: Path) -> None:
    for name in ("first", "second"):
        (tmp_path / name).mkdir()
    svc = start_service(tmp_path / "first", viewer=False)
    port = svc.url.rsplit(":", 1)[1]
    second: LiveService | None = None
    try:
        async with dashboard(svc) as page:
            await expect(page.locator("#links-state")).to_have_text("links up")
            # the page's own first loads are in (not cut off by the kill below)
            await expect(page.locator("#runs tbody")).to_contain_text("no runs recorded yet")
            svc.stop(signal.SIGKILL)  # no goodbye: the socket just closes

            banner = page.locator("#dead-banner")
            await expect(banner).to_be_visible(timeout=30_000)
            await expect(banner).to_contain_text(re.compile(
                rf"The service is not answering \(since {WALL_TIME}\) — "
                "the hand's state is unknown"
            ))  # fmt: skip
            await expect(page.locator("#links-state")).not_to_contain_text("up")
            await expect(page.locator("#ws-state")).not_to_have_text("live")
            # the socket's retry counts down (it said the same figure until the retry)
            ws_state = page.locator("#ws-state")
            counting = re.compile(r"no service — retry in ([2-9]|\d\d+) s")
            await expect(ws_state).to_have_text(counting, timeout=30_000)
            n = int(re.findall(r"\d+", await ws_state.inner_text())[0])
            await expect(ws_state).to_have_text(f"no service — retry in {n - 1} s")
            await expect(page.locator("#run-state")).to_have_text("unknown")
            await expect(page.locator("body")).to_have_class(re.compile("service-dead"))
            for sel in ("#start", "#stop", "#estop-release", "#open-hand", "#object-select",
                        "#params-apply"):  # fmt: skip
                await expect(page.locator(sel)).to_be_disabled()
            # … but not the E-STOP: the page may be wrong about the service, the click tries;
            # when it fails the page says to use the hand's own switch, until dismissed
            async with page.expect_request(lambda r: r.url.endswith("/api/estop")):
                await page.click("#estop")
            failed = page.locator("#errors .toast", has_text="use the hand's own emergency-stop")
            await expect(failed).to_be_visible()
            await page.evaluate("window.sdh2debug.expireToasts(Date.now() + 3600e3)")
            await expect(failed).to_be_visible()
            await page.evaluate("window.sdh2.lastError = null")
            # the live widgets are greyed out and take no clicks
            style = await page.evaluate(
                "() => { const s = getComputedStyle(document.querySelector('main'));"
                " return [s.filter, s.pointerEvents]; }"
            )
            assert "grayscale" in style[0] and style[1] == "none", style
            assert not (await counters(page))["serviceAlive"]
            await screenshot(page, "dead-service")

            # a service on the same port again: everything comes back by itself
            # (the page asks again where the 3-D view is: the service may be another one)
            viewer_asked = page.expect_request(
                lambda r: r.url.endswith("/api/viewer"), timeout=90_000
            )
            async with viewer_asked:
                second = start_service(tmp_path / "second", viewer=False, extra=("--port", port))
                assert second.url == svc.url
                await expect(banner).to_be_hidden(timeout=60_000)
                await page.wait_for_function(
                    "window.sdh2.ws === 'open' && window.sdh2.serviceAlive", timeout=30_000
                )
            await expect(page.locator("#viewer-note")).to_contain_text(
                "The 3-D view is not available"
            )
            await expect(page.locator("#viewer-note")).to_contain_text("the view's process ended")
            await expect(page.locator("#links-state")).to_have_text("links up")
            # its tooltip is no longer the dead service's
            await expect(page.locator("#links-state")).to_have_attribute("title", re.compile("up"))
            await expect(page.locator("body")).not_to_have_class(re.compile("service-dead"))
            await expect(page.locator("#start")).to_be_enabled()
            await expect(page.locator("#estop")).to_be_enabled()

            # a frozen service: the socket stays open but goes silent, the status poll gets no
            # answer; the same banner, and the same recovery when it runs again
            second.proc.send_signal(signal.SIGSTOP)
            try:
                await expect(banner).to_be_visible(timeout=30_000)
                await expect(page.locator("#links-state")).to_have_text("links unknown")
            finally:
                second.proc.send_signal(signal.SIGCONT)
            await expect(banner).to_be_hidden(timeout=60_000)
            await page.wait_for_function(
                "window.sdh2.ws === 'open' && window.sdh2.serviceAlive", timeout=30_000
            )
            await expect(page.locator("#links-state")).to_have_text("links up")
            assert (await counters(page))["lastError"] is None
    finally:
        svc.stop()
        if second is not None:
            assert second.stop() == 0, "".join(second.log)


# The last status the page got, with a run the e-stop ended: fed latched, then released as
# the service says it (the run stays "e-stopped", `estopped` false), in one turn (no real status
# comes between); the header's run state after each.
RUN_ESTOPPED_THEN_RELEASED = """() => {
  const st = structuredClone(window.sdh2debug.status());
  st.run = {id: 9999, state: 'e-stopped', stroke: 0, strokes_total: 3, iteration: 37,
            status: 'e-stopped', message: 'emergency stop'};
  st.estopped = true;
  st.estop = {since: '2026-12-07T10:00:00.000+0000', reason: 'e-stop requested',
              hand_reached: true};
  const header = () => {
    const e = document.querySelector('#run-state');
    return {text: e.textContent, state: e.dataset.state, colour: getComputedStyle(e).color};
  };
  window.sdh2debug.onMessage({type: 'status', status: st});
  const latched = header();
  window.sdh2debug.onMessage({type: 'status', status: {...st, estopped: false, estop: null}});
  return {latched, released: header()};
}"""
LATCHED_RED = "rgb(255, 138, 128)"  # web/style.css: #run-state[data-state="e-stopped"]


async def test_the_header_shows_the_release_as_soon_as_the_status_says_so(page: Any) -> None:
    shown = await page.evaluate(RUN_ESTOPPED_THEN_RELEASED)
    assert shown["latched"] == {"text": "e-stopped", "state": "e-stopped",
                                "colour": LATCHED_RED}, shown  # fmt: skip
    assert shown["released"]["text"] == "e-stop released", shown
    assert shown["released"]["state"] == "estop-released", shown
    assert shown["released"]["colour"] != LATCHED_RED, shown


# The object readout (web/readout.js) rendered into a copy of #object-readout for each case
# [sample, true turn (null: not known now; "none": no truth, as on a real hand)]: its fields.
READOUT_OF = """async (cases) => {
  const { showObject } = await import('/web/readout.js');
  const el = document.querySelector('#object-readout').cloneNode(true);
  return cases.map(([s, truly]) => {
    showObject(el, s, truly === 'none' ? undefined : truly);
    return ['.obj-class', '.obj-size', '.obj-rot', '.obj-contacts']
      .map((sel) => el.querySelector(sel).textContent);
  });
}"""


async def test_the_object_readout_shows_every_unknown_value_as_a_dash(page: Any) -> None:
    nothing = {"iteration": 3, "object_class": None, "class_confidence": None, "size_a": None,
               "size_b": None, "rotation_est": None, "contact1_kind": None,
               "contact2_kind": None, "radius1": None, "radius2": None}  # fmt: skip
    box = {**nothing, "object_class": "box", "class_confidence": 0.73, "size_a": 52.7,
           "rotation_est": -3.04, "contact1_kind": "curved", "contact2_kind": "flat"}  # fmt: skip
    circle = {**box, "object_class": "circle", "size_a": None, "class_confidence": None,
              "contact1_kind": "curved", "radius1": 13.75}  # fmt: skip
    shown = await page.evaluate(READOUT_OF, [
        [None, "none"], [None, None], [nothing, None], [box, None], [box, -3.14], [circle, "none"],
    ])  # fmt: skip
    assert shown == [
        ["object –", "size –", "turned –", "A – · B –"],
        ["object –", "size –", "turned – (true –)", "A – · B –"],
        ["object –", "size –", "turned – (true –)", "A – · B –"],
        ["box 73 %", "52.7 × – mm", "turned -3.0° (true –)", "A curved, r – mm · B flat"],
        ["box 73 %", "52.7 × – mm", "turned -3.0° (true -3.1°)", "A curved, r – mm · B flat"],
        ["circle – %", "r – mm", "turned -3.0°", "A curved, r 13.8 mm · B flat"],
    ], shown
    # the page as it is served says the same before any sample
    served = await page.evaluate("""async () => {
      const doc = new DOMParser().parseFromString(await (await fetch('/')).text(), 'text/html');
      return ['.obj-class', '.obj-size', '.obj-rot', '.obj-contacts']
        .map((sel) => doc.querySelector(sel).textContent);
    }""")
    assert served == shown[0], served


async def test_the_true_turn_is_not_kept_past_an_estop_release(
    service: LiveService, page: Any
) -> None:
    """In simulation the readout's true turn is the live run's; once the e-stop that ended the
    run is released it is no longer known ("–"), not the value it had at the e-stop."""
    rot = page.locator("#object-readout .obj-rot")
    with _runs_of(service, ESTOP_RUN_CYCLES):
        async with service.client() as c:
            await start_run(c, obj="egg")
        # rolling: the estimate and the truth beside it
        await expect(rot).to_have_text(re.compile(r"\(true -?\d+\.\d°\)$"), timeout=RUN_TIMEOUT_MS)
        await page.click("#estop")
        await page.wait_for_function(
            "document.querySelector('#estop').classList.contains('latched')"
            " && window.sdh2debug.status().run.state === 'e-stopped'"
        )
        # latched: the run's last sample is still shown with the truth at that sample
        await expect(rot).to_have_text(re.compile(r"\(true -?\d+\.\d°\)$"))
        estimate = await page.inner_text("#object-readout .obj-class")
        await page.click("#estop-release")
        await page.wait_for_function("window.sdh2debug.status().estopped === false")
        await expect(rot).to_have_text(re.compile(r"^turned -?\d+\.\d° \(true –\)$"))
        # the recognition's estimate of the last sample stays
        assert await page.inner_text("#object-readout .obj-class") == estimate


async def test_the_view_s_note_replaces_its_frame_once_the_status_says_it_is_gone(
    page: Any,
) -> None:
    """A 3-D view whose process died left its frame saying "Connecting…" for ever: the page
    asked where the view is only at start and on reconnecting. The status now says."""
    await page.route(re.compile(r"/api/viewer$"), lambda r: r.fulfill(json={"url": None}))
    await page.evaluate("""() => {  // a frame showing a view, as GET /api/viewer had said
      const f = document.querySelector('#viewer');
      f.hidden = false;
      f.dataset.url = 'http://127.0.0.1:9/';
      const st = {...structuredClone(window.sdh2debug.status()), viewer: false};
      window.sdh2debug.onMessage({type: 'status', status: st});
    }""")
    await expect(page.locator("#viewer-note")).to_contain_text("the view's process ended")
    await expect(page.locator("#viewer")).to_be_hidden()


# A live run's two samples fed with the object's true angle ψ at each, then ψ after the run
# (the object let go, put back, or swapped for another) and the page back to live from a replay,
# in one turn: the readout's turn each time.
TURN_AFTER_THE_RUN = """() => {
  const d = window.sdh2debug;
  const rot = () => document.querySelector('#object-readout .obj-rot').textContent;
  const sim = (psi) => d.onMessage({type: 'sim', truth: {object: 'egg', held: true,
    dropped: false, in_fixture: false, pose: [20, 120, psi], outline: [], contacts: []}});
  const sample = (iteration) => d.onMessage({type: 'sample', run_id: 987654,
    sample: {iteration, t: iteration / 30, rotation_est: 5.0}});
  sim(0.0); sample(1); sim(0.1); sample(2);
  const atRun = rot();
  sim(1.0);
  document.querySelector('#back-to-live').click();
  return {atRun, after: rot()};
}"""


async def test_the_true_turn_shown_is_the_runs_last_sample_s(page: Any) -> None:
    """Back to live from a replay, the readout showed the run's last sample beside ψ now minus
    ψ at its grasp: after the run that is the object let go, put back or another one."""
    await page.route(
        re.compile(r"/api/runs/987654/"),
        lambda r: r.fulfill(
            json={"samples": [], "total": 0, "next": None, "truth": [], "outline": None}
        ),
    )
    shown = await page.evaluate(TURN_AFTER_THE_RUN)
    assert shown == {"atRun": "turned 5.0° (true 5.7°)", "after": "turned 5.0° (true 5.7°)"}


# The last status the page got with the e-stop latched since `since`, fed, and the real one
# again, in one turn: the latch's line and the E-STOP's tooltip meanwhile.
LATCHED_SINCE = """(since) => {
  const real = window.sdh2debug.status();
  const st = {...structuredClone(real), estopped: true,
              estop: {since, reason: 'e-stop requested', hand_reached: true}};
  window.sdh2debug.onMessage({type: 'status', status: st});
  const shown = {latch: document.querySelector('#estop-latch').textContent,
                 title: document.querySelector('#estop').title};
  window.sdh2debug.onMessage({type: 'status', status: real});
  return shown;
}"""


async def test_every_wall_clock_time_is_shown_one_way(page: Any) -> None:
    started, ended = "2026-12-07T10:00:00.000+0000", "2026-12-07T10:02:03+00:00"
    row = {"id": 7, "started_at": started, "ended_at": ended, "status": "completed",
           "iterations": 12, "meta": {"object": {"name": "egg"}}, "summary": {}}  # fmt: skip
    await page.route(RUN_LIST, lambda r: r.fulfill(json=[row], headers={"X-Total-Count": "1"}))
    await page.click("#runs-refresh")
    cells = page.locator("#runs tbody tr[data-run-id='7'] td")
    # the run history's start and end
    await expect(cells.nth(1)).to_have_text(await local_time(page, started))
    await expect(cells.nth(2)).to_have_text(await local_time(page, ended))
    # the e-stop's latch: the line next to the E-STOP and its tooltip
    at = await local_time(page, started)
    shown = await page.evaluate(LATCHED_SINCE, started)
    assert shown["latch"].startswith(f"latched {at} — e-stop requested"), shown
    assert f"latched since {at} (e-stop requested)" in shown["title"], shown
    assert re.fullmatch(WALL_TIME, at), at


async def test_the_object_picker_is_disabled_while_the_estop_is_latched(
    service: LiveService, page: Any
) -> None:
    picker = page.locator("#object-select")
    await expect(picker).to_be_enabled()
    await page.click("#estop")
    try:
        await page.wait_for_function("window.sdh2debug.status().estopped === true")
        await expect(picker).to_be_disabled()
        why = re.compile("^Release the e-stop first: while it is latched the object stays")
        await expect(picker).to_have_attribute("title", why)  # the tooltip …
        await expect(picker).to_have_accessible_description(why)  # … and a screen reader's
        # the API refuses it too (and the picker still shows the object there is)
        name = httpx.get(service.url + "/api/sim/object").json()["object"]["name"]
        other = "cylinder" if name != "cylinder" else "egg"
        r = httpx.put(service.url + "/api/sim/object", json={"name": other},
                      headers=service.headers())  # fmt: skip
        assert r.status_code == 409 and "e-stop is latched" in r.json()["error"], r.text
        await expect(picker).to_have_value(name)
    finally:
        await page.click("#estop-release")
    await expect(picker).to_be_enabled()
    await expect(picker).to_have_attribute("title", "object between the fingertips (simulation)")
