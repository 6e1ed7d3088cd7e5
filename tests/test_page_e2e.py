"""End-to-end tests of the officer's page (frontend/) against the real server.

A short small-boat recording is simulated once per test session, ``berthing-aid serve`` runs on
free loopback ports, and Debian's chromium (driven by playwright) opens the page. The page
exposes what it has on screen as ``window.berthing`` (the frame header last drawn, the
image→canvas mapping, the canvas colours), so pixel checks use the very message that was drawn.

Every state is saved as a screenshot in ``tests/artifacts/`` for a human look.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = Path("/usr/bin/chromium")
ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
ROOT = Path(__file__).resolve().parent.parent
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 "--disable-quic"]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not CHROMIUM.exists(),
                       reason="end-to-end page tests need Debian's chromium at /usr/bin/chromium "
                              "(apt-get install chromium); playwright cannot download browsers "
                              "here"),
]

playwright_api = pytest.importorskip("playwright.sync_api")


# ----------------------------------------------------------------------------- fixtures


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get_json(url: str, method: str = "GET") -> dict | None:
    req = urllib.request.Request(url, method=method)
    with urllib.request.urlopen(req, timeout=5) as res:
        body = res.read()
    return json.loads(body) if body else None


@pytest.fixture(scope="session")
def recording(sim_recording: Path) -> Path:
    return sim_recording


FAULTY = "small-boat-12s-imu-gap"
FROZEN = "small-boat-12s-video-frozen"


@pytest.fixture(scope="session")
def faulty_recordings(recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory with damaged copies of the recording: 2 s of IMU missing from 6 s; the
    camera frozen on one picture from 6 s for 3 s (re-encoded: refreshed at its keyframes)."""
    from recordings.faults import inject

    root = tmp_path_factory.mktemp("faulty")
    inject(recording, "imu-gap:6:2", root / FAULTY)
    inject(recording, "video-frozen:6:3", root / FROZEN)
    return root


_SERVER_PIDS: dict[str, int] = {}  # base URL → the server's process (to suspend it)


@contextlib.contextmanager
def _serving(recording: Path, log_name: str, env: dict[str, str] | None = None,
             recordings_dir: Path | None = None) -> Iterator[str]:
    """``berthing-aid serve`` on free loopback ports (the damaged copies listed too); yields
    its base URL."""
    port, viser_port = _free_port(), _free_port()
    log = (ARTIFACTS / log_name)
    ARTIFACTS.mkdir(exist_ok=True)
    with log.open("w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "backend.cli", "serve", str(recording), "--host", "127.0.0.1",
             "--port", str(port), "--viser-port", str(viser_port),
             *(["--recordings-dir", str(recordings_dir)] if recordings_dir else []),
             # the 12 s recording's heading converges to 1° only after ~15 s: wider for the page
             "--heading-alert-limit", "3"],
            cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env={**os.environ,
                                                                 "PYTHONUNBUFFERED": "1",
                                                                 **(env or {})})
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 60
            while True:
                if proc.poll() is not None:
                    pytest.fail(f"server exited ({proc.returncode}): {log.read_text()}")
                with contextlib.suppress(OSError):
                    urllib.request.urlopen(base + "/openapi.json", timeout=5).close()
                    break
                if time.monotonic() > deadline:
                    pytest.fail(f"server did not answer within 60 s: {log.read_text()}")
                time.sleep(0.3)
            _SERVER_PIDS[base] = proc.pid
            yield base
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


@pytest.fixture(scope="session")
def server(recording: Path, faulty_recordings: Path) -> Iterator[str]:
    with _serving(recording, "server.log", recordings_dir=faulty_recordings) as base:
        yield base


@pytest.fixture(scope="session")
def browser() -> Iterator:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


def _open_page(browser, server: str, width: int, height: int, query: str = ""):
    page = browser.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server + "/" + query)
    page.errors = errors  # checked at the end of each test
    return page


@pytest.fixture
def page(browser, server: str) -> Iterator:
    """The page at 1920x1080 with its own replay session (deleted afterwards: the server
    allows only a few at once)."""
    pg = _open_page(browser, server, 1920, 1080)
    yield pg
    _close(pg, server)


def _close(pg, server: str) -> None:
    with contextlib.suppress(Exception):
        sid = pg.evaluate("() => window.berthing.session && window.berthing.session.id")
        if sid:
            _get_json(f"{server}/api/sessions/{sid}", method="DELETE")
    errors = pg.errors
    pg.close()
    assert not errors, f"uncaught errors in the page: {errors}"


# ------------------------------------------------------------------------------ helpers


def shot(page, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"))


def frame(page) -> dict | None:
    return page.evaluate("() => window.berthing.frame")


def _wait(page, condition: str, timeout_s: float, value: str = "true"):
    """Wait for a JS condition on ``b = window.berthing``; returns ``value`` (a JS expression)
    evaluated in the same task as the condition held. A replay that stopped with an error
    fails at once with the server's message rather than after the timeout."""
    try:
        handle = page.wait_for_function(
            f"() => {{ const b = window.berthing; if (!b) return false; const f = b.frame; "
            f"if (b.session && b.session.state === 'error') return {{error: b.session.error}}; "
            f"return ({condition}) ? {{value: {value}}} : false; }}",
            timeout=timeout_s * 1000)
    except playwright_api.TimeoutError:
        shot(page, "FAILED_wait")
        seen = page.evaluate("""() => ({toasts: window.berthing.toasts, t: window.berthing.frame?.t,
            session: window.berthing.session?.state, link: window.berthing.stats.connection})""")
        pytest.fail(f"timed out after {timeout_s} s waiting for {condition}; page: {seen}")
    out = handle.json_value()
    if "error" in out:
        pytest.fail(f"the replay stopped with an error: {out['error']}")
    return out.get("value")


def wait_frame(page, predicate: str = "f => f", timeout_s: float = 30.0) -> dict:
    """The frame on screen once it satisfies ``predicate`` (JS arrow function of it)."""
    return _wait(page, f"!!f && ({predicate})(f)", timeout_s, "f")


def wait_trusted(page, timeout_s: float = 30.0) -> dict:
    """A frame whose fused pose the page trusts (GNSS compass fixed, fusion running)."""
    return _wait(page, "!!f && !!f.overlay && b.trust.trusted", timeout_s, "f")


def pause(page) -> None:
    page.click("#play")
    _wait(page, "b.session.state === 'paused'", 15)
    page.wait_for_timeout(300)  # the last frame sent before the pause has arrived


def css_point(page, canvas_id: str, u: float, v: float) -> tuple[float, float]:
    """Page coordinates of image pixel (u, v) of the video."""
    box = page.locator(f"#{canvas_id}").bounding_box()
    view = page.evaluate("() => window.berthing.view")
    return box["x"] + view["ox"] + u * view["scale"], box["y"] + view["oy"] + v * view["scale"]


def range_digits(d: float) -> str:
    """A distance as the page writes it: cm below 5 m, dm below 50 m, metres beyond."""
    return f"{d:.{2 if abs(d) < 5 else 1 if abs(d) < 50 else 0}f}"


def parse_color(css: str) -> tuple[int, int, int]:
    css = css.strip()
    if css.startswith("#"):
        return tuple(int(css[i:i + 2], 16) for i in (1, 3, 5))
    return tuple(int(float(x)) for x in re.findall(r"[\d.]+", css)[:3])


# JS: sample the overlay canvas at grid nodes of the frame on screen, in the same task as
# reading the frame (no redraw can come in between). Nodes near other drawings (points,
# predicted outlines, targets) are skipped; "background" samples are spots far from every
# line and point, where nothing may be drawn.
SAMPLE_GRID = """() => {
  const b = window.berthing, f = b.frame, v = b.view;
  const cv = document.getElementById('overlay');
  const ctx = cv.getContext('2d', {willReadFrequently: true});
  // the most covered pixel of the 3x3 around the point: lines are antialiased
  const px = (u, w) => {
    const d = ctx.getImageData(Math.round((v.ox + u * v.scale) * v.dpr) - 1,
                               Math.round((v.oy + w * v.scale) * v.dpr) - 1, 3, 3).data;
    let best = 0;
    for (let i = 4; i < d.length; i += 4) if (d[i + 3] > d[best + 3]) best = i;
    return d.slice(best, best + 4);
  };
  const segs = [];
  const addLines = (lines) => {
    for (const l of lines) for (let i = 1; i < l.length; i++) segs.push([l[i-1], l[i]]);
  };
  const ov = f.overlay.video;
  for (const p of ov.prediction) addLines(p.polylines);
  addLines(ov.hull || []);
  if (f.overlay.berth) addLines(f.overlay.berth.polylines);
  const otherSegs = segs.splice(0);
  addLines(ov.grid.lines);
  const gridSegs = segs.splice(0);
  const dSeg = (p, [a, c]) => {
    const dx = c[0] - a[0], dy = c[1] - a[1];
    const t = Math.max(0, Math.min(1, ((p[0]-a[0])*dx + (p[1]-a[1])*dy) / (dx*dx + dy*dy || 1)));
    return Math.hypot(p[0] - a[0] - t*dx, p[1] - a[1] - t*dy);
  };
  const near = (p, r) => ov.points.uv.some(q => Math.hypot(q[0]-p[0], q[1]-p[1]) < r)
    || otherSegs.some(s => dSeg(p, s) < r)
    || (f.overlay.targets || []).some(t => t.uv && Math.hypot(t.uv[0]-p[0], t.uv[1]-p[1]) < 40);
  const nodes = ov.grid.nodes.uv.filter(p => p[0] > 3 && p[1] > 3 && p[0] < f.width - 3
                                        && p[1] < f.height - 3 && !near(p, 6));
  const grid = nodes.slice(0, 40).map(p => ({uv: p, rgba: Array.from(px(p[0], p[1]))}));
  const background = [];
  for (let w = 5; w < f.height; w += 23) for (let u = 5; u < f.width; u += 31) {
    const p = [u, w];
    if (gridSegs.every(s => dSeg(p, s) > 6) && !near(p, 8) && background.length < 60)
      background.push({uv: p, rgba: Array.from(px(u, w))});
  }
  return {t: f.t, frame: f.frame, trusted: b.trust.trusted, grid, background,
          gridColor: b.colors.grid, nodes: ov.grid.nodes.uv.length};
}"""


# -------------------------------------------------------------------------------- tests


def test_page_loads_and_frames_play(page) -> None:
    f1 = wait_frame(page)
    f2 = wait_frame(page, f"f => f.t > {f1['t']} + 1.0", timeout_s=15)
    assert f2["frame"] > f1["frame"], "the frame index advances while playing"
    assert page.evaluate("() => window.berthing.stats.connection") == "live"
    assert page.locator("#st-conn .v").inner_text() == "live"
    assert page.locator("#time").inner_text() != "0:00.0"
    # one session of the only recording, playing
    assert page.locator("#recording").input_value() == "small-boat-12s"
    assert page.locator("#play").inner_text() == "❚❚"
    wait_trusted(page)
    # the layout fits 1920x1080 without scrolling
    assert page.evaluate("() => document.scrollingElement.scrollHeight") <= 1080
    shot(page, "01_playing_1920")


def test_grid_drawn_where_the_pose_says(page) -> None:
    wait_trusted(page)
    page.wait_for_function("() => window.berthing.frame.overlay.video.grid.nodes.uv.length > 10")
    for _ in range(20):  # a frame drawn trusted (the 12 s recording's trust may flicker)
        s = page.evaluate(SAMPLE_GRID)
        if s["trusted"]:
            break
        page.wait_for_timeout(250)
    assert s["trusted"]
    assert len(s["grid"]) >= 5, f"too few grid nodes free of other drawings: {s['nodes']}"
    want = parse_color(s["gridColor"])
    assert want[1] > 200 and want[0] < 80 and want[2] < 120, "the grid colour is green"

    def green(rgba):
        r, g, b, a = rgba
        return a > 100 and g > 180 and g > r + 80 and g > b + 60

    hits = [n for n in s["grid"] if green(n["rgba"])]
    assert len(hits) >= 0.8 * len(s["grid"]), f"grid nodes not green: {s['grid'][:8]}"
    # and nothing is drawn away from the grid lines and points
    assert s["background"], "no free background spot found"
    painted = [b for b in s["background"] if b["rgba"][3] > 0]
    assert len(painted) <= 0.05 * len(s["background"]), f"painted off the grid: {painted[:5]}"
    shot(page, "02_grid")


def test_overlay_greys_out_when_untrusted(page) -> None:
    """The same overlay with the fusion still aligning (no compass fix): grey, and the notice
    over the video says why."""
    wait_trusted(page)
    page.wait_for_function("() => window.berthing.frame.overlay.video.grid.nodes.uv.length > 10")
    pause(page)  # no newer frame may replace the one we draw
    page.evaluate("""() => { const f = window.berthing.frame;
      window.berthing.show({...f, status: {...f.status, phase: 'aligning', compass_fixed: false,
        integrity: {...f.status.integrity, mode: 'aligning', trusted: false,
                    reasons: ['no GNSS compass fix: heading from the course over ground']}}});
    }""")
    assert not page.evaluate("() => window.berthing.trust.trusted")
    notice = page.locator("#untrusted")
    assert notice.is_visible() and "Aligning" in notice.inner_text()
    assert page.locator("#st-compass").get_attribute("data-level") == "bad"
    s = page.evaluate(SAMPLE_GRID)
    drawn = [n["rgba"] for n in s["grid"] if n["rgba"][3] > 100]
    assert len(drawn) >= 0.8 * len(s["grid"]) > 0
    for r, g, b, _a in drawn:
        assert max(r, g, b) - min(r, g, b) < 30, f"grid not grey when untrusted: {drawn[:5]}"
    shot(page, "02_untrusted_grey")


def test_no_position_yet_says_why(page) -> None:
    """No position and no fault (a live start waiting for the satellites' orbits): the notice
    gives the fusion's own words, not a bare "No position"."""
    wait_trusted(page)
    pause(page)
    page.evaluate("""() => { const f = window.berthing.frame;
      window.berthing.show({...f, pose: null, status: {...f.status, phase: 'initialising',
        message: 'compass: no standalone position yet: broadcast ephemerides of 2 of 12 '
                 + 'satellites (waiting for their navigation messages)',
        integrity: {...f.status.integrity, mode: 'no position', trusted: false, reasons: [],
                    hpl_m: null, heading_pl_deg: null}}}); }""")
    notice = page.locator("#untrusted").inner_text()
    assert notice.startswith("Overlay not reliable: No position — compass: no standalone"), notice
    assert "ephemerides of 2 of 12" in notice


def test_a_live_input_down_is_named_first_on_the_record_chip(browser, server: str) -> None:
    """Which input is down is what a narrow header must not cut (at 1400 px a user trial
    read "… · down: r"): it comes first on the chip."""
    pg = _open_page(browser, server, 1400, 900)
    try:
        wait_frame(pg)
        pause(pg)
        pg.evaluate("""() => { const f = window.berthing.frame;
          window.berthing.show({...f, live: {recording: true, record_s: 75,
                                             inputs_down: ['rx2', 'camera']}}); }""")
        chip = pg.locator("#st-rec")
        assert chip.locator(".v").inner_text().startswith("rx2, camera down · ")
        box, header = chip.bounding_box(), pg.locator(".status").bounding_box()
        assert box is not None and header is not None
        # the names, the first part of the chip, are on screen
        assert box["x"] + 0.3 * box["width"] <= min(1400, header["x"] + header["width"])
        shot(pg, "08c_live_input_down_1400")
    finally:
        _close(pg, server)


def test_wide_approach_sigmas_fit_the_berth_card_at_1400(browser, server: str) -> None:
    """An INS fault widens the approach speeds' σ to decimetres a second ("99 cm/s ±53"):
    at 1400 px the stern's column was pushed out of the berth card (its header read "STE",
    its σ and direction cut off: a second user trial). Every figure stays inside the card."""
    pg = _open_page(browser, server, 1400, 900)
    try:
        wait_trusted(pg)
        pause(pg)
        pg.evaluate("""() => { const f = window.berthing.frame;
          window.berthing.show({...f, overlay: {...f.overlay, berth: {
            line_ne: [[0, 0], [10, 0]], method: 'ned', source: 'typed', bow_distance_m: 102.3,
            stern_distance_m: 125.4, bow_distance_sigma_m: 2.0, stern_distance_sigma_m: 2.1,
            bow_approach_mps: 0.99, stern_approach_mps: -1.13, bow_approach_sigma_mps: 0.53,
            stern_approach_sigma_mps: 0.88, along_berth_mps: 0.13, angle_deg: 2.2,
            angle_sigma_deg: 0.2, time_to_contact_s: 400}}}); }""")
        card = pg.locator("#stern-speed").locator("xpath=ancestor::section[1]")
        assert pg.locator("#stern-speed").inner_text().replace("\n", " ") == "▲113cm/s OPENING ±88"
        cb = card.bounding_box()
        for sel in ("#bow-speed", "#stern-speed", "#stern-dist", "#bow-dist"):
            box = pg.locator(sel).bounding_box()
            assert box is not None and cb is not None
            assert box["x"] + box["width"] <= cb["x"] + cb["width"] + 1, (sel, box, cb)
        assert card.evaluate("e => e.scrollWidth <= e.clientWidth"), "the card overflows"
        shot(pg, "05b_berth_card_wide_sigmas_1400")
    finally:
        _close(pg, server)


def test_the_rate_of_turn_shows_its_sigma_when_it_matters(page) -> None:
    """A gyro fault widens the rate of turn's σ (``integrity.YawStepCheck``: 0.5°/s, 30°/min):
    the ROT readout says ±30; a usual σ (a few hundredths of a °/s) is not printed."""
    wait_trusted(page)
    pause(page)  # no newer frame may replace the one we show
    page.evaluate("""() => { const f = window.berthing.frame;
      window.berthing.show({...f, pose: {...f.pose, rate_of_turn_dps: 0.15,
                                         rate_of_turn_std_dps: 0.5}}); }""")
    assert page.locator("#rot").inner_text().replace("\n", " ").strip() == "9°/min S ±30"
    page.evaluate("""() => { const f = window.berthing.frame;
      window.berthing.show({...f, pose: {...f.pose, rate_of_turn_dps: 0.15,
                                         rate_of_turn_std_dps: 0.01}}); }""")
    assert page.locator("#rot").inner_text().replace("\n", " ").strip() == "9°/min S"


def test_an_excluded_vo_is_said_and_the_overlay_stays_usable(page) -> None:
    """The engine excluded the VO (its travel disagreed with the carrier-phase track,
    ``estimator.vo_coupling.VoConsistency``) while GNSS and IMU still hold the state: the VO
    chip says so in amber, the notice over the video gives the fault, and the overlay keeps
    its colours (trusted by the protection levels)."""
    wait_trusted(page)
    pause(page)  # no newer frame may replace the one we show
    page.evaluate("""() => { const f = window.berthing.frame;
      window.berthing.show({...f, status: {...f.status, vo_status: 'excluded',
        integrity: {...f.status.integrity, trusted: true,
                    reasons: ['VO direction of travel 20.7° off over 1 s: VO excluded']}}});
    }""")
    assert page.evaluate("() => window.berthing.trust.trusted")
    chip = page.locator("#st-vo")
    assert chip.inner_text().endswith("excluded") and chip.get_attribute("data-level") == "warn"
    notice = page.locator("#untrusted")
    assert notice.is_visible() and notice.get_attribute("data-level") == "warn"
    assert "VO excluded" in notice.inner_text()
    assert "Visual odometry excluded" in (notice.get_attribute("title") or "")
    shot(page, "02b_vo_excluded")


def test_a_sensor_fault_is_declared_on_the_page_within_a_second(browser, server: str) -> None:
    """2 s of IMU missing from 6 s: the page says "no position" within a second, greys the
    overlay, raises a sounding integrity alarm the officer acknowledges, and trusts the pose
    again once the fusion has recovered."""
    pg = _open_page(browser, server, 1920, 1080, f"?recording={FAULTY}")
    try:
        assert wait_frame(pg, "f => f.t > 4 && b.trust.trusted", timeout_s=60)
        # at a quarter speed: the fault lasts 2 s of the recording, 8 s to look at it (the
        # "within a second" is in recording time)
        pg.select_option("#speed", "0.25")
        _wait(pg, "b.session.speed === 0.25", 10)
        pg.evaluate("() => document.body.click()")  # the user gesture that lets audio start
        lost = _wait(pg, "!!f && f.t >= 6.0 && !b.trust.trusted", 30, "f")
        assert lost["t"] <= 6.0 + 0.3 + 1.0, lost["t"]  # IMU silent for 0.3 s, then declared
        ig = lost["status"]["integrity"]
        assert ig["mode"] == "no position" and not ig["trusted"]
        assert any("IMU" in r for r in ig["reasons"])
        assert "No position" in pg.locator("#untrusted").inner_text()
        assert pg.locator("#st-integrity").get_attribute("data-level") == "bad"
        alarm = _wait(pg, "b.alarms.list.some(a => a.kind === 'integrity' && a.active)", 10,
                      "b.alarms")
        assert alarm["sounding"] and alarm["beeps"] >= 1
        assert pg.locator("#alarms").is_visible()
        # Half a second on, the fusion's last state is left behind: no stale pose looking
        # live (overlay, berth and navigation figures) while the page says why.
        gone = _wait(pg, "!!f && f.t >= 6.6 && f.t < 7.9", 30, "f")
        assert gone["pose"] is None and gone["overlay"] is None, gone["pose"]
        assert gone["status"]["phase"] == "degraded"
        assert gone["status"]["integrity"]["mode"] == "no position"
        assert "No position" in pg.locator("#untrusted").inner_text()
        assert pg.locator("#st-phase").inner_text().endswith("degraded")
        assert pg.locator("#hdg").inner_text() == "–"
        # and the API says the same: no current pose, a berth line without figures
        sid = pg.evaluate("() => window.berthing.session.id")
        with pytest.raises(urllib.error.HTTPError) as refused:
            _get_json(f"{server}/api/sessions/{sid}/pose")
        assert refused.value.code == 409 and "no current pose" in refused.value.read().decode()
        berth = _get_json(f"{server}/api/sessions/{sid}/berth-line")
        assert berth["line_ne"] is not None and berth["bow_distance_m"] is None, berth
        fusion = _get_json(f"{server}/api/sessions/{sid}")["fusion"]
        assert fusion["phase"] == "degraded" and not fusion["integrity"]["trusted"], fusion
        # the API's alarm list keeps what the alarm was raised for and how often it came back
        listed = _get_json(f"{server}/api/sessions/{sid}/alarms")["alarms"]
        integrity = next(a for a in listed if a["kind"] == "integrity")
        assert integrity["first_message"].startswith("Integrity lost: ") \
            and isinstance(integrity["repeats"], int), integrity
        shot(pg, "07_integrity_alarm")
        # the integrity alarm and the fault behind it both sound: one acknowledgement for all
        pg.locator("#alarms li[data-kind=integrity] button").click()
        _wait(pg, "b.alarms.list.some(a => a.kind === 'integrity' && a.acknowledged)", 5)
        pg.click("#alarm-ack-all")
        _wait(pg, "!b.alarms.sounding", 5)
        back = _wait(pg, "!!f && f.t > 8.5 && b.trust.trusted", 40, "f")
        assert back["status"]["integrity"]["mode"] == "fused"
        # the trajectory has no row from the gap's stale state: times only increase
        track = _get_json(f"{server}/api/sessions/{sid}/trajectory")
        t = np.array(track["t"])
        assert np.all(np.diff(t) > 0) and not np.any((t > 6.6) & (t < 8.0)), t[55:90]
        _wait(pg, "!b.alarms.list.some(a => a.kind === 'integrity')", 5)
        shot(pg, "07_integrity_recovered")
    finally:
        _close(pg, server)


def test_a_frozen_camera_is_said_and_nothing_is_drawn_on_its_old_picture(browser,
                                                                         server: str) -> None:
    """The camera repeats one picture from 6 s for 3 s while the pose goes on (a user trial:
    the freeze was declared, then cleared at each of the copy's keyframes, and at 6.5 s the
    page drew the overlay of now on the picture of 6 s, the VO chip green, no notice). The
    whole freeze is one: the VO chip says the frames are skipped, nothing is drawn on the old
    picture, the notice says how old it is, a click on it is refused; after it, all as
    before."""
    pg = _open_page(browser, server, 1280, 800, f"?recording={FROZEN}")
    try:
        assert wait_frame(pg, "f => f.t > 4 && b.trust.trusted", timeout_s=60)
        pg.select_option("#speed", "0.5")
        frozen = []
        for t in (6.6, 7.3, 8.0, 8.7):  # the keyframes refresh the copy every 1.2 s
            f = wait_frame(pg, f"f => f.t >= {t}", timeout_s=30)
            frozen.append(f)
            assert f["t"] < 9.0, f["t"]
            assert f["picture_t"] is not None and 5.8 <= f["picture_t"] <= 6.1, f["picture_t"]
            assert f["status"]["vo_status"] == "skipped", f["status"]
            video = f["overlay"]["video"]
            assert video["hull"] == [] and video["grid"]["lines"] == [], t
            assert pg.locator("#st-vo .v").inner_text() == "skipped"
            assert "Camera picture" in pg.locator("#untrusted").inner_text()
        shot(pg, "07_video_frozen")
        sid = pg.evaluate("() => window.berthing.session.id")
        # a click on a frozen frame (the one on screen a moment ago): refused
        body = json.dumps({"u": 480, "v": 300, "frame_time": frozen[-1]["t"]}).encode()
        req = urllib.request.Request(f"{server}/api/sessions/{sid}/targets", data=body,
                                     headers={"Content-Type": "application/json"},
                                     method="POST")
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(req, timeout=30)
        assert refused.value.code == 409 and "frozen" in refused.value.read().decode()
        pg.select_option("#speed", "1")
        back = wait_frame(pg, "f => f.t >= 10.5", timeout_s=30)
        assert back["picture_t"] is None and back["status"]["vo_status"] != "skipped", back
        assert back["overlay"]["video"]["grid"]["lines"], "the overlay is drawn again"
    finally:
        _close(pg, server)


# JS: the overlay canvas around structure points clear of the grid, hull and prediction lines
# (8 px), by kind: the centre pixel's alpha and the most opaque pixel within 4 CSS px. An
# obstacle is sampled whatever its neighbours (a filled disc is opaque at its centre); any
# other point only when no drawn point (obstacles; with ``all``, every point) is within 12 px.
SAMPLE_POINT_CENTRES = """(all) => {
  const b = window.berthing, f = b.frame, v = b.view;
  const ctx = document.getElementById('overlay').getContext('2d', {willReadFrequently: true});
  const pts = f.overlay.video.points, segs = [];
  const lines = [...f.overlay.video.grid.lines, ...(f.overlay.video.hull || []),
                 ...f.overlay.video.prediction.flatMap(p => p.polylines)];
  for (const l of lines) for (let i = 1; i < l.length; i++) segs.push([l[i-1], l[i]]);
  const dSeg = (p, [a, c]) => {
    const dx = c[0] - a[0], dy = c[1] - a[1];
    const t = Math.max(0, Math.min(1, ((p[0]-a[0])*dx + (p[1]-a[1])*dy) / (dx*dx + dy*dy || 1)));
    return Math.hypot(p[0] - a[0] - t*dx, p[1] - a[1] - t*dy);
  };
  const out = {obstacle: [], other: []};
  pts.uv.forEach((p, i) => {
    if (segs.some(s => dSeg(p, s) < 8)) return;
    if (!pts.obstacle[i] && pts.uv.some((q, j) => j !== i && (all || pts.obstacle[j])
                                        && Math.hypot(q[0]-p[0], q[1]-p[1]) < 12)) return;
    const x = Math.round((v.ox + p[0] * v.scale) * v.dpr);
    const y = Math.round((v.oy + p[1] * v.scale) * v.dpr);
    const r = Math.round(4 * v.dpr);
    const d = ctx.getImageData(x - r, y - r, 2 * r + 1, 2 * r + 1).data;
    let most = 0;
    for (let k = 3; k < d.length; k += 4) most = Math.max(most, d[k]);
    const centre = d[(r * (2 * r + 1) + r) * 4 + 3];
    (pts.obstacle[i] ? out.obstacle : out.other).push({centre, most});
  });
  return out;
}"""


def test_only_obstacles_are_drawn_unless_all_points_are_asked_for(page) -> None:
    """By default the officer sees the converged points above the water near the ship and
    the berth (filled, in their distance band's colour); the rest (converging, on the water,
    far away) only on demand, as faint hollow rings."""
    wait_trusted(page)
    # (the 12 s recording ends 45 m off the quay: few of its points are obstacles yet)
    wait_frame(page, "f => f.overlay && f.overlay.video.points.obstacle.includes(true) "
               "&& f.overlay.video.points.obstacle.includes(false)", timeout_s=40)
    pause(page)
    s = page.evaluate(SAMPLE_POINT_CENTRES, False)
    assert len(s["obstacle"]) >= 1 and len(s["other"]) >= 3, s
    assert sorted(p["centre"] for p in s["obstacle"])[len(s["obstacle"]) // 2] > 150, s
    assert sorted(p["most"] for p in s["other"])[len(s["other"]) * 3 // 4] < 30, s
    page.check("#all-points")
    s = page.evaluate(SAMPLE_POINT_CENTRES, True)
    assert len(s["other"]) >= 3, s
    assert sorted(p["centre"] for p in s["other"])[len(s["other"]) // 2] < 60, s  # hollow
    assert sorted(p["most"] for p in s["other"])[len(s["other"]) // 2] > 60, s  # but drawn
    page.uncheck("#all-points")
    # the legend gives the fixed bands, in the colours the points are drawn in
    bands = page.locator("#legend-bands .band")
    assert bands.count() == 7 and bands.nth(0).inner_text() == "0–2"
    assert bands.nth(6).inner_text() == "100+ m"


def test_birdseye_shows_the_ship(page) -> None:
    wait_trusted(page)
    sample = """() => {
      const cv = document.getElementById('birdseye');
      const ctx = cv.getContext('2d');
      const c = ctx.getImageData(Math.round(cv.width / 2), Math.round(cv.height / 2), 1, 1).data;
      const corner = ctx.getImageData(Math.round(cv.width * 0.1), Math.round(cv.height * 0.9),
                                      1, 1).data;
      return {centre: Array.from(c), corner: Array.from(corner), ship: window.berthing.colors.ship,
              bg: window.berthing.colors.planBg, t: window.berthing.frame.t,
              heading: window.berthing.frame.overlay.birdseye.heading_deg};
    }"""
    s = page.evaluate(sample)
    ship = parse_color(s["ship"])
    assert all(abs(a - b) <= 12 for a, b in zip(s["centre"][:3], ship, strict=True)), s
    assert s["corner"][:3] != list(ship), "the ship colour is not everywhere"
    shot(page, "03_birdseye_north_up")
    # head-up: the ship is still at the centre, the plan turns with it
    page.click("#orient")
    assert page.locator("#orient").inner_text() == "Head-up"
    page.wait_for_timeout(300)
    s2 = page.evaluate(sample)
    assert all(abs(a - b) <= 12 for a, b in zip(s2["centre"][:3], ship, strict=True)), s2
    assert page.evaluate("() => window.berthing.plan.rot") == pytest.approx(
        s2["heading"] * 3.141592653589793 / 180, abs=0.05)
    shot(page, "03_birdseye_head_up")
    page.click("#orient")


def _quay_point(f: dict) -> tuple[int, list[float]]:
    """A port-structure point on the video near the image centre (id, uv)."""
    pts = f["overlay"]["video"]["points"]
    w, h = f["width"], f["height"]
    best = min(range(len(pts["uv"])),
               key=lambda i: abs(pts["uv"][i][0] - w / 2) + 0.3 * abs(pts["uv"][i][1] - h / 2))
    return pts["id"][best], pts["uv"][best]


def test_click_on_the_quay_measures_a_locked_distance(page) -> None:
    wait_trusted(page)
    wait_frame(page, "f => f.overlay && f.overlay.video.points.uv.length > 20")
    # Paused, the frame we pick the point on is the one the click designates on (playing, a
    # newer frame can arrive between reading it and the click: the scene pans ~4 px a frame).
    pause(page)
    f = frame(page)
    pid, uv = _quay_point(f)
    page.mouse.click(*css_point(page, "overlay", *uv))
    f1 = wait_frame(page, "f => f.overlay.targets.length === 1")
    t1 = f1["overlay"]["targets"][0]
    assert t1["distance_m"] > 5
    page.wait_for_selector("#targets li[data-id]")
    assert re.search(r"^\d+(\.\d\d?)? m$", page.locator("#targets li[data-id] .tdist").inner_text())
    # with its 1-σ, as the stream gives it
    sub = page.locator("#targets li[data-id] .tsub").inner_text()
    sigma = re.search(r"±(\d+\.\d\d?) m", sub)  # cm below 10 m, dm beyond
    assert sigma and t1["distance_sigma_m"] is not None, sub
    assert abs(float(sigma.group(1)) - t1["distance_sigma_m"]) < 0.2 * t1["distance_sigma_m"] + 0.02
    shot(page, "04_target_designated")

    # frames later the label is still there, on the same quay point, with a new distance
    page.click("#play")
    f2 = wait_frame(page, f"f => f.t > {f1['t']} + 2.0 && f.overlay.targets.length === 1")
    t2 = f2["overlay"]["targets"][0]
    assert t2["id"] == t1["id"] and t2["visible"]
    assert t2["distance_m"] > 1.0
    pts = f2["overlay"]["video"]["points"]
    if pid in pts["id"]:  # the anchoring structure point is still mapped: the target is on it
        anchor = pts["uv"][pts["id"].index(pid)]
        assert abs(anchor[0] - t2["uv"][0]) < 25 and abs(anchor[1] - t2["uv"][1]) < 25, \
            (anchor, t2["uv"])
    # the label is drawn on the overlay next to the target: its dark box is there
    label = page.evaluate("""() => {
      const b = window.berthing, t = b.frame.overlay.targets[0], v = b.view;
      const cv = document.getElementById('overlay');
      const x = (v.ox + t.uv[0] * v.scale + 30) * v.dpr;
      const y = (v.oy + t.uv[1] * v.scale - 16) * v.dpr;
      return Array.from(cv.getContext('2d').getImageData(Math.round(x), Math.round(y), 1, 1).data);
    }""")
    assert label[3] > 150, f"no distance label at the target: {label}"
    # ... and it reads the distance with its σ, as the list does
    drawn, shown_t = page.evaluate("""() => [window.berthing.labels.map((l) => l[4]),
                                            window.berthing.frame.overlay.targets[0]]""")
    m = re.fullmatch(r"(\S+)  (\S+) ±(\d+\.\d\d?) m", drawn[0])
    assert m, drawn
    assert m[1] == (shown_t["label"] or shown_t["id"])
    assert m[2] == range_digits(shown_t["distance_m"])
    assert float(m[3]) == pytest.approx(shown_t["distance_sigma_m"], abs=0.051)
    assert page.locator("#targets li[data-id]").count() == 1
    # the list shows the distance of the frame on screen
    shown = page.evaluate("""() => [
      document.querySelector('#targets li[data-id] .tdist').textContent,
                                    window.berthing.frame.overlay.targets[0].distance_m]""")
    assert shown[0] == f"{range_digits(shown[1])} m"
    shot(page, "04_target_frames_later")

    # a second target, then remove the first
    uv2 = f2["overlay"]["video"]["points"]["uv"][0]
    page.mouse.click(*css_point(page, "overlay", *uv2))
    wait_frame(page, "f => f.overlay.targets.length === 2")
    page.locator(f"#targets li[data-id='{t1['id']}'] button").click()
    f3 = wait_frame(page, "f => f.overlay.targets.length === 1 "
                          f"&& f.overlay.targets[0].id !== '{t1['id']}'")
    assert f3["overlay"]["targets"][0]["id"] != t1["id"]

    # three targets a few pixels apart (a ladder and the fenders beside it): each label is
    # drawn where no other covers it (ids no server target has: the page hides a target it
    # has asked the server to remove until the server's frames no longer carry it, and the
    # first one, T1, may still be on its way out)
    boxes = page.evaluate("""() => {
      const f = structuredClone(window.berthing.frame), t = f.overlay.targets[0];
      f.overlay.targets = [0, 1, 2].map((k) => ({...t, id: `near${k}`, label: `T${k}`,
        uv: [f.width / 2 + 6 * k, f.height / 2 + 4 * k], visible: true}));
      window.berthing.show(f);
      return window.berthing.labels;
    }""")
    assert len(boxes) == 3
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1], (a, b)

    # a lost target says why in the list (and is not drawn on the video)
    lost = page.evaluate("""() => {
      const f = structuredClone(window.berthing.frame), t = f.overlay.targets[0];
      f.overlay.targets = [{...t, id: "lost0", label: "T9 (lost)", uv: null, visible: false,
        status: "lost", reason: "look-alikes in reach: not taken back"}];
      window.berthing.show(f);
      return [document.querySelector('#targets li[data-id="lost0"] .tsub').textContent,
              window.berthing.labels.length];
    }""")
    assert lost[0].endswith(" · lost: look-alikes in reach: not taken back"), lost
    assert lost[1] == 0, lost
    shot(page, "04_target_lost_reason")


def test_berth_line_from_two_clicks_gives_bow_and_stern(page) -> None:
    # the recording's own berth line is drawn on the quay's water line: the officer's two
    # clicks go on that line, so the figures must come out (nearly) the same
    f = wait_frame(page, "f => f.overlay && f.overlay.berth && f.overlay.berth.polylines.length "
                         "&& f.t > 3")
    pause(page)
    f = frame(page)
    ref = f["overlay"]["berth"]
    drawn = sorted((p for line in ref["polylines"] for p in line
                    if 20 < p[0] < f["width"] - 20 and 0 < p[1] < f["height"]),
                   key=lambda p: p[0])
    assert len(drawn) >= 2, ref["polylines"]
    a, b = drawn[0], drawn[-1]

    page.click("#berth-clear")
    wait_frame(page, "f => f.overlay.berth === null")
    assert page.locator("#bow-dist").inner_text() == "–"
    page.click("#berth-set")
    assert page.locator("#hint").is_visible()
    page.mouse.click(*css_point(page, "overlay", *a))
    page.wait_for_timeout(200)
    shot(page, "05_berth_first_click")
    page.mouse.click(*css_point(page, "overlay", *b))
    f2 = wait_frame(page, "f => f.overlay.berth && f.overlay.berth.bow_distance_m != null")
    berth = f2["overlay"]["berth"]
    assert berth["source"] == "image"
    for end in ("bow", "stern"):
        # a pixel near the horizon is worth metres at 60 m from a camera 1 m above the water
        assert berth[f"{end}_distance_m"] == pytest.approx(ref[f"{end}_distance_m"], rel=0.15)
        assert berth[f"{end}_approach_mps"] == pytest.approx(ref[f"{end}_approach_mps"], abs=0.1)
    # heading ~25 deg towards the quay: the bow is nearer and both ends are closing
    assert 0 < berth["bow_distance_m"] < berth["stern_distance_m"]
    assert berth["bow_approach_mps"] > 0.2 and berth["stern_approach_mps"] > 0.2
    # at 50 m and beyond the distance is given to the metre, with its σ
    bow = page.locator("#bow-dist").inner_text().split("\n")[0]
    assert bow == f"{range_digits(berth['bow_distance_m'])}m", bow
    speed = page.locator("#bow-speed").inner_text().replace("\n", "")
    assert speed.startswith(f"▼{berth['bow_approach_mps'] * 100:.0f}cm/s"), speed
    # ~1 m/s towards the quay, but 50-60 m off: beyond the default approach-limit table
    assert "alarm" not in page.locator("#bow-speed").get_attribute("class")
    assert "alarm" not in page.locator("#video-wrap").get_attribute("class")
    ttc = page.locator("#ttc").inner_text()
    assert ttc.endswith("s") or ttc.endswith("min"), ttc
    shot(page, "05_berth_line_video")

    # playing on, the server's frames carry the new line (drawn by the server's projection)
    page.click("#play")
    f3 = wait_frame(page, f"f => f.t > {f2['t']} + 0.5 && f.overlay.berth "
                          "&& f.overlay.berth.polylines.length")
    assert f3["overlay"]["berth"]["bow_distance_m"] < berth["bow_distance_m"], "closing"

    # the berth line from two clicks in the plan instead
    before = json.dumps(f3["overlay"]["birdseye"]["berth_line"], separators=(",", ":"))
    page.click("#berth-set")
    box = page.locator("#birdseye").bounding_box()
    page.mouse.click(box["x"] + box["width"] * 0.2, box["y"] + box["height"] * 0.25)
    page.mouse.click(box["x"] + box["width"] * 0.8, box["y"] + box["height"] * 0.25)
    f4 = wait_frame(page, "f => f.overlay.berth && f.overlay.berth.source === 'ned' "
                          f"&& JSON.stringify(f.overlay.birdseye.berth_line) !== '{before}'")
    line = f4["overlay"]["birdseye"]["berth_line"]
    pos = f4["overlay"]["birdseye"]["position"]
    # clicked a quarter of the plan's height above its centre (north-up): north of the ship
    assert line[0][0] > pos[0] and line[1][0] > pos[0]
    assert f4["overlay"]["berth"]["bow_distance_m"] > 0
    page.wait_for_timeout(300)
    shot(page, "05_berth_line_plan")
    page.click("#berth-clear")
    wait_frame(page, "f => f.overlay && f.overlay.berth === null")
    assert page.locator("#bow-dist").inner_text() == "–"


def test_pause_and_seek(page) -> None:
    wait_trusted(page)
    pause(page)
    assert page.locator("#play").inner_text() == "▶"
    t_paused = frame(page)["t"]
    page.wait_for_timeout(1200)
    assert frame(page)["t"] == t_paused, "paused: the picture stays"
    shot(page, "06_paused")

    # seek back to 4 s while paused: the frame at 4 s is shown
    page.evaluate("""() => { const s = document.getElementById('seek');
      s.value = '4'; s.dispatchEvent(new Event('input'));
      s.dispatchEvent(new Event('change')); }""")
    f = wait_frame(page, "f => Math.abs(f.t - 4.0) < 0.15", timeout_s=30)
    assert page.evaluate("() => window.berthing.session.state") == "paused"
    assert page.locator("#time").inner_text() == "0:04.0"
    shot(page, "06_seek_4s")

    # seek to before the GNSS compass fix: the overlay says why it is missing
    page.evaluate("""() => { const s = document.getElementById('seek');
      s.value = '0.5'; s.dispatchEvent(new Event('change')); }""")
    f = wait_frame(page, "f => Math.abs(f.t - 0.5) < 0.15", timeout_s=30)
    if f["pose"] is None or not page.evaluate("() => window.berthing.trust.trusted"):
        notice = page.locator("#untrusted")
        assert notice.is_visible()
        assert "not reliable" in notice.inner_text()
        shot(page, "06_seek_initialising")

    # play resumes
    page.click("#play")
    page.wait_for_function("() => window.berthing.frame.t > 1.5", timeout=15000)


def test_speed_and_a_second_screen(page, browser, server: str) -> None:
    wait_frame(page)
    page.select_option("#speed", "2")
    _wait(page, "b.session.speed === 2", 10)
    sid = page.evaluate("() => window.berthing.session.id")
    # a second screen watches the same replay (?session=): same frames, same controls
    second = _open_page(browser, server, 1280, 800, f"?session={sid}")
    try:
        wait_frame(second)
        assert second.evaluate("() => window.berthing.session.id") == sid
        assert second.locator("#speed").input_value() == "2"
        # a speed the menu lacks, set through the API: the menu shows it, not its last value
        with urllib.request.urlopen(urllib.request.Request(
                f"{server}/api/sessions/{sid}/control", method="POST",
                data=json.dumps({"action": "speed", "speed": 8}).encode(),
                headers={"Content-Type": "application/json"}), timeout=5):
            pass
        _wait(second, "b.session.speed === 8", 10)
        second.wait_for_timeout(300)
        assert second.locator("#speed").input_value() == "8"
        pause(second)
        _wait(page, "b.session.state === 'paused'", 10)
        assert page.locator("#play").inner_text() == "▶"
        assert not second.errors
    finally:
        second.close()
    # leaving did not delete the session it only watched
    assert _get_json(f"{server}/api/sessions/{sid}")["id"] == sid


def test_reloading_the_first_screen_keeps_the_session_a_second_one_joined(
        page, browser, server: str) -> None:
    """The page that opened a session deletes it as it closes, to free the server — but a
    second screen that joined it (with its locked targets) keeps it: reloading the first
    screen told the second "Session closed" and took its targets (a user trial). The
    session goes once its last watcher has."""
    wait_frame(page)
    sid = page.evaluate("() => window.berthing.session.id")
    second = _open_page(browser, server, 1280, 800, f"?session={sid}")
    try:
        wait_frame(second)
        page.reload()
        wait_frame(page)
        assert page.evaluate("() => window.berthing.session.id") != sid  # a session of its own
        assert _get_json(f"{server}/api/sessions/{sid}")["id"] == sid
        t0 = second.evaluate("() => window.berthing.frame.t")
        _wait(second, f"!!f && f.t > {t0} + 0.5", 10)  # still playing on the second screen
        assert not second.errors
    finally:
        second.close()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:  # the last watcher gone: the session goes
        try:
            _get_json(f"{server}/api/sessions/{sid}")
        except urllib.error.HTTPError as exc:
            assert exc.code == 404
            break
        time.sleep(0.2)
    else:
        raise AssertionError("the session outlived its last watcher")


CONTROL_TOKEN, VIEW_TOKEN = "control-token-for-the-page-test", "view-token-for-the-page-test"


def test_the_page_takes_its_token_from_the_address_and_a_viewer_only_watches(
        browser, recording: Path) -> None:
    """A server that requires tokens (as off loopback): the page without one says what to do;
    with the control token from the address fragment it plays (the token leaves the address
    bar); a second screen with the read-only token watches the same session, cannot steer."""
    env = {"BERTHING_AID_TOKEN": CONTROL_TOKEN, "BERTHING_AID_VIEW_TOKEN": VIEW_TOKEN}
    with _serving(recording, "server-tokens.log", env) as base:
        bare = _open_page(browser, base, 1280, 800)
        try:
            bare.wait_for_function("() => window.berthing.toasts.some("
                                   "t => t.includes('needs an access token'))", timeout=10000)
        finally:
            bare.close()
        officer = _open_page(browser, base, 1280, 800, f"#token={CONTROL_TOKEN}")
        second = None
        try:
            wait_frame(officer)
            assert "token" not in officer.url
            assert officer.evaluate("() => sessionStorage.getItem('berthing.token')") \
                == CONTROL_TOKEN
            sid = officer.evaluate("() => window.berthing.session.id")
            second = _open_page(browser, base, 1280, 800, f"?session={sid}#token={VIEW_TOKEN}")
            first = wait_frame(second)
            assert second.evaluate("() => window.berthing.session.id") == sid
            wait_frame(second, f"f => f.frame > {first['frame']}")  # the stream takes it too
            second.click("#play")  # pause: refused for a read-only token
            second.wait_for_function("() => window.berthing.toasts.some("
                                     "t => t.includes('read-only'))", timeout=10000)
            assert officer.evaluate("() => window.berthing.session.state") == "playing"
            assert not second.errors and not officer.errors
        finally:
            if second is not None:
                second.close()
            officer.close()


def test_frames_that_stop_coming_grey_the_page_within_a_second(page, server: str) -> None:
    """The server stops sending frames while the replay plays (here suspended: hung, or a
    live session whose sensors all went quiet): within about a second the page says so and
    no longer trusts what it shows, as if the fusion had declared it; with frames again,
    trusted again."""
    wait_trusted(page)
    os.kill(_SERVER_PIDS[server], signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        page.wait_for_function("() => window.berthing.stats.connection === 'stale' "
                               "&& !window.berthing.trust.trusted", timeout=5000)
        assert time.monotonic() - t0 < 1.8
        assert "No new frames" in page.locator("#untrusted").inner_text()
        assert page.locator("#st-integrity").inner_text().endswith("no data")
        assert "unreliable" in (page.locator(".side").get_attribute("class") or "")
        # the figures are of then, not now: none shown (the picture stays, said frozen)
        for fig in ("#hdg", "#sog", "#rot", "#bow-dist"):
            assert page.locator(fig).inner_text().strip() == "–", fig
        assert page.locator("#berth-method").inner_text() == "no new data"
        for chip in ("#st-phase", "#st-compass", "#st-sats", "#st-vo"):  # of then: not green
            assert page.locator(chip).get_attribute("data-level") == "stale", chip
        shot(page, "08_frames_stopped")
    finally:
        os.kill(_SERVER_PIDS[server], signal.SIGCONT)
    page.wait_for_function("() => window.berthing.stats.connection === 'live' "
                           "&& window.berthing.trust.trusted", timeout=20000)
    page.wait_for_function("() => document.getElementById('hdg').innerText.includes('°')",
                           timeout=5000)


def test_a_page_that_falls_behind_says_so_and_withholds_the_figures(page) -> None:
    """The browser itself falls behind (starved of CPU: a user trial's page showed data 8 s
    old, the server and another client 0.6 s): each picture takes 2.5 s to decode here. The
    page measures how much later than the best case it shows a frame (its server time and
    the fastest transport seen, so the two machines' clocks may differ) and, beyond 1.5 s,
    says so, stops trusting and withholds the figures; decoding quickly again, it recovers."""
    wait_trusted(page)
    page.evaluate("""() => { window._bitmap = window.createImageBitmap;
      window.createImageBitmap = async (b) => {
        await new Promise((r) => setTimeout(r, 2500)); return window._bitmap(b); }; }""")
    try:
        page.wait_for_function("() => window.berthing.stats.connection === 'behind' "
                               "&& !window.berthing.trust.trusted", timeout=15000)
        notice = page.locator("#untrusted").inner_text()
        assert "s behind the sensors — figures withheld" in notice, notice
        assert page.locator("#hdg").inner_text().strip() == "–"
        shot(page, "08b_display_behind")
    finally:
        page.evaluate("() => { window.createImageBitmap = window._bitmap; }")
    page.wait_for_function("() => window.berthing.stats.connection === 'live' "
                           "&& window.berthing.trust.trusted", timeout=20000)


def test_stream_reconnects(page) -> None:
    f1 = wait_frame(page)
    page.evaluate("() => window.berthing.dropConnection()")
    page.wait_for_function("() => window.berthing.stats.connection !== 'live'", timeout=5000)
    page.wait_for_function(f"() => window.berthing.stats.connection === 'live' "
                           f"&& window.berthing.frame.frame > {f1['frame']} + 5", timeout=15000)


def test_viewer_opens(page, server: str) -> None:
    wait_frame(page)
    page.click("#tab-3d")
    assert page.locator("#view-3d").is_visible()
    page.wait_for_function("() => document.getElementById('viewer').src.startsWith('http')",
                           timeout=10000)
    src = page.locator("#viewer").get_attribute("src")
    assert page.locator("#viewer-link").get_attribute("href") == src
    with urllib.request.urlopen(src, timeout=10) as res:
        assert res.status == 200
        assert b"<html" in res.read(4096).lower()
    sid = page.evaluate("() => window.berthing.session.id")
    info = _get_json(server + "/api/viewer")
    assert info["session"] == sid, "the 3-D view shows this page's session"
    page.wait_for_timeout(2500)
    shot(page, "07_viewer")
    page.click("#tab-ar")
    assert page.locator("#view-ar").is_visible()


# JS: every painted pixel of the overlay and plan canvases, as [r, g, b] (alpha-weighted
# over black, as the night page shows them), and the canvas colours in use.
SAMPLE_CANVASES = """() => {
  const out = {};
  for (const id of ['overlay', 'birdseye']) {
    const cv = document.getElementById(id);
    const d = cv.getContext('2d', {willReadFrequently: true})
      .getImageData(0, 0, cv.width, cv.height).data;
    const px = [];
    for (let i = 0; i < d.length; i += 4 * 7) {  // every 7th pixel
      if (d[i + 3] < 40) continue;
      const a = d[i + 3] / 255;
      px.push([d[i] * a, d[i + 1] * a, d[i + 2] * a]);
    }
    out[id] = px;
  }
  return out;
}"""


def _bright_white(rgb) -> bool:
    return min(rgb) > 170


def _saturated_green(rgb) -> bool:
    r, g, b = rgb
    return g > 90 and g > 1.4 * r + 20 and g > 1.4 * b + 20


def test_night_mode_has_no_bright_white_or_saturated_green(page) -> None:
    """Night mode as on bridge equipment: dimmed, red/amber, nothing bright white or green
    anywhere — the overlay and plan colours sampled from the canvases, the whole page from a
    screenshot — and still readable."""
    wait_trusted(page)
    wait_frame(page, "f => f.overlay.video.grid.lines.length > 5 "
                     "&& f.overlay.video.points.obstacle.includes(true)")
    day_bg = page.evaluate("() => getComputedStyle(document.body).backgroundColor")
    pause(page)
    page.check("#all-points")  # every kind of point drawn
    day = page.evaluate(SAMPLE_CANVASES)
    # the day overlay does have its bright green grid and white outlines: the check can fail
    assert sum(map(_saturated_green, day["overlay"])) > 50
    page.click("#theme")
    assert page.evaluate("() => document.documentElement.dataset.theme") == "night"
    page.wait_for_timeout(400)
    night = page.evaluate(SAMPLE_CANVASES)
    for name in ("overlay", "birdseye"):
        px = night[name]
        assert len(px) > 200, name
        white = [p for p in px if _bright_white(p)]
        green = [p for p in px if _saturated_green(p)]
        assert len(white) <= 0.001 * len(px), (name, white[:5])
        assert len(green) <= 0.001 * len(px), (name, green[:5])
    s = page.evaluate("""() => {
      const st = (sel, p) => getComputedStyle(document.querySelector(sel))[p];
      return {bg: st('body', 'backgroundColor'), text: st('#bow-dist', 'color'),
              panel: st('.card', 'backgroundColor'), video: st('#video', 'filter'),
              ship: window.berthing.colors.ship};
    }""")
    assert s["bg"] != day_bg and parse_color(s["bg"]) == (0, 0, 0)
    r, g, b = parse_color(s["text"])
    assert r > 2 * g and r > 2 * b and r < 240, f"night text is dim red/amber: {s['text']}"
    assert sum(parse_color(s["panel"])) < 40
    assert max(parse_color(s["ship"])) < 200, "no bright ship at night"
    assert "brightness" in s["video"], "the video is dimmed at night"
    # the whole page as the officer sees it (video dimmed, controls, seek bar, legend)
    ARTIFACTS.mkdir(exist_ok=True)
    path = ARTIFACTS / "08_night.png"
    page.screenshot(path=str(path))
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"), dtype=float)[::3, ::3].reshape(-1, 3)
    white = (img.min(axis=1) > 170).mean()
    green = ((img[:, 1] > 90) & (img[:, 1] > 1.4 * img[:, 0] + 20)
             & (img[:, 1] > 1.4 * img[:, 2] + 20)).mean()
    assert white < 0.0005 and green < 0.0005, (white, green)
    page.click("#theme")
    assert page.evaluate("() => document.documentElement.dataset.theme") == "day"


def test_approach_alarms_go_amber_then_red_as_the_ship_closes(page) -> None:
    """The officer sets the approach-speed limits by distance in the page's table; as the
    ship closes the berth (~0.8 m/s, slowing to 0.5 by the recording's end) the bow's
    approach goes amber within the outer band and red within the inner one, in the panel,
    around the video and in the alarm list (red sounds until acknowledged). The inner band
    starts 1.8 m closer, where the approach is still ~0.8 m/s (2.6 m closer, with red above
    80 cm/s, the ship had slowed to 0.69 m/s there and red never came)."""
    wait_trusted(page)
    wait_frame(page, "f => f.overlay.berth && f.overlay.berth.bow_distance_m != null "
                     "&& f.overlay.berth.bow_approach_mps > 0.5 && b.trust.trusted")
    pause(page)
    page.evaluate("() => document.body.click()")  # the user gesture that lets audio start
    d0 = frame(page)["overlay"]["berth"]["bow_distance_m"]
    amber_within, red_within = round(d0 - 0.8, 1), round(d0 - 1.8, 1)
    page.click("#limits summary")
    rows = page.locator("#limits-body tr")
    # replace the table by two rows: amber above 50 cm/s within amber_within, red above 60
    # within red_within (the outer row's red limit is out of reach)
    for i in range(rows.count()):
        for inp in rows.nth(i).locator("input").all():
            inp.fill("")
    for i, row in enumerate([(amber_within, 50, 400), (red_within, 50, 60)]):
        for inp, value in zip(rows.nth(i).locator("input").all(), row, strict=True):
            inp.fill(str(value))
    page.click("#limits-save")
    _wait(page, "document.querySelector('#limit-now').textContent.includes('none')", 5)
    page.click("#play")
    amber = _wait(page, "!!f && f.alarms.some(a => a.kind === 'approach-bow' "
                        "&& a.severity === 'warning')", 15, "f")
    pause(page)  # looked at on a still picture (at 1x red is less than 2 s away)
    d = amber["overlay"]["berth"]["bow_distance_m"]
    assert red_within - 0.3 < d < amber_within + 0.3, (d, amber_within)
    speed = page.locator("#bow-speed")
    _wait(page, "document.querySelector('#bow-speed').classList.contains('warning')", 2)
    assert "warning" in page.locator("#video-wrap").get_attribute("class")
    assert page.locator("#alarms li[data-kind=approach-bow].warning").is_visible()
    assert page.evaluate("() => window.berthing.alarms.sounding") is False  # amber: a chime
    assert page.evaluate("() => window.berthing.alarms.chimes") >= 1
    shot(page, "10_approach_amber")
    page.click("#play")
    red = _wait(page, "!!f && f.alarms.some(a => a.kind === 'approach-bow' "
                      "&& a.severity === 'alarm')", 15, "f")
    pause(page)
    assert red["overlay"]["berth"]["bow_distance_m"] < red_within + 0.3
    _wait(page, "document.querySelector('#bow-speed').classList.contains('alarm')", 2)
    assert "alarm" in speed.get_attribute("class")
    assert "alarm" in page.locator("#video-wrap").get_attribute("class").split()
    alarms = _wait(page, "b.alarms.sounding", 3, "b.alarms")
    assert alarms["beeps"] >= 1
    assert "cm/s" in page.locator("#alarms li[data-kind=approach-bow]").inner_text()
    shot(page, "10_approach_red")
    page.locator("#alarms li[data-kind=approach-bow] button").click()
    _wait(page, "!b.alarms.sounding", 5)


def test_layout_1280x800(browser, server: str) -> None:
    pg = _open_page(browser, server, 1280, 800)
    try:
        wait_trusted(pg)
        wait_frame(pg, "f => f.overlay.video.points.uv.length > 20")
        pg.wait_for_timeout(500)
        assert pg.evaluate("() => document.scrollingElement.scrollHeight") <= 800
        assert pg.evaluate("() => document.scrollingElement.scrollWidth") <= 1280
        for sel in ("#video", "#birdseye", "#bow-dist", "#stern-speed", "#hdg", "#rot",
                    "#sog", "#cog", "#targets", "#play", "#seek", "#speed", "#recording",
                    "#theme", "#st-scale"):
            box = pg.locator(sel).bounding_box()
            assert box and box["width"] > 0 and box["height"] > 0, sel
            assert box["x"] >= 0 and box["y"] >= 0, sel
            assert box["x"] + box["width"] <= 1280 + 1 and box["y"] + box["height"] <= 800 + 1, \
                (sel, box)
        # no read-out runs past its own box (the SOG's m/s ran 18 px past the panel's edge,
        # where a σ after it would be cut off)
        spill = pg.evaluate("""() => [...document.querySelectorAll('.side .mid, .side .big')]
            .filter((e) => {
                const card = e.closest('.card').getBoundingClientRect();
                const r = e.getBoundingClientRect();
                return e.scrollWidth > e.clientWidth + 1 || r.right > card.right - 4; })
            .map((e) => [e.id, e.textContent, e.getBoundingClientRect().right,
                         e.closest('.card').getBoundingClientRect().right])""")
        assert not spill, spill
        video = pg.locator("#video").bounding_box()
        assert video["width"] >= 800, "the video stays the largest thing on the screen"
        assert not pg.locator("#st-rec").is_visible(), "a replay is not being recorded"
        # no fault on the undamaged recording; the approach-speed alarms are the berthing's
        # own (this one closes at ~80 cm/s, the warning limit within 50 m, and may say so)
        alarms = pg.evaluate("() => window.berthing.alarms.list.map(a => a.kind)")
        assert all(k.startswith("approach-") for k in alarms), alarms
        assert pg.locator("#alarms").is_visible() == bool(alarms), alarms
        shot(pg, "09_layout_1280x800")
    finally:
        _close(pg, server)


def test_layout_on_a_phone(browser, server: str) -> None:
    """At 390x844 (a phone upright) the page is one column that scrolls: nothing wider than
    the screen, every read-out and control reachable (a user trial found the two-column
    page 1147 px wide, the integrity chip off-screen and the targets over the controls)."""
    pg = _open_page(browser, server, 390, 844)
    try:
        wait_frame(pg)
        pg.wait_for_timeout(500)
        assert pg.evaluate("() => document.scrollingElement.scrollWidth") <= 390
        boxes = {}
        for sel in ("#video", "#st-integrity", "#st-phase", "#play", "#seek", "#speed",
                    "#birdseye", "#bow-dist", "#hdg", "#targets", "#theme"):
            pg.locator(sel).scroll_into_view_if_needed()
            box = pg.locator(sel).bounding_box()
            assert box and box["width"] > 0 and box["height"] > 0, sel
            boxes[sel] = box
            page_x = box["x"] + pg.evaluate("() => window.scrollX")
            assert page_x >= 0 and page_x + box["width"] <= 390 + 1, (sel, box)
        video = boxes["#video"]
        assert video["width"] >= 380, "the video takes the screen's width"
        shot(pg, "10_layout_phone")
    finally:
        _close(pg, server)


# ------------------------------------------------- the bundled recording: the quay foot truth

DEFAULT_RECORDING = ROOT / "recordings" / "default"
QUAY_TIME_S = 60.0  # the bow 13 m off the quay: its face reconstructed, converged


@pytest.fixture(scope="module")
def default_server() -> Iterator[str]:
    if not (DEFAULT_RECORDING / "manifest.json").exists():
        pytest.skip("the bundled recording is not here")
    with _serving(DEFAULT_RECORDING, "server-default.log") as base:
        yield base


def _click_berth(page, clicks) -> dict:
    before = (frame(page)["overlay"].get("berth") or {}).get("line_ne")
    page.click("#berth-set")
    for u, v in clicks:
        page.mouse.click(*css_point(page, "overlay", u, v))
    return wait_frame(page, "f => f.overlay.berth && f.overlay.berth.source === 'image' && "
                            f"JSON.stringify(f.overlay.birdseye.berth_line) !== "
                            f"'{json.dumps(before, separators=(',', ':'))}'", timeout_s=15)


def test_berth_clicks_on_the_true_quay_foot_give_the_true_bow_distance(browser,
                                                                        default_server: str):
    """On the bundled (simulated) recording at 60 s, the officer seeks there (the badge shows
    the target and the progress), then clicks the quay foot where the reference pose projects
    it: the line is fitted to the quay face and the bow distance is the true one within
    max(0.15 m, 1 %); clicks slipped by 3 px give the same within 0.3 m."""
    from evaluation.truth import quay_foot_clicks
    from recordings.format import load

    rec = load(DEFAULT_RECORDING)
    pg = _open_page(browser, default_server, 1920, 1080)
    try:
        wait_frame(pg)
        pause(pg)
        tic = time.monotonic()
        pg.evaluate(f"""() => {{ const s = document.getElementById('seek');
          s.value = '{QUAY_TIME_S}'; s.dispatchEvent(new Event('change')); }}""")
        # the badge while the seek runs: its target and progress (unless the look-ahead
        # engine has been there already, when it is done within a couple of seconds)
        badges = set()
        while time.monotonic() - tic < 300:
            seen = pg.evaluate(f"""() => ({{
              badge: document.getElementById('replay-badge').hidden ? null
                     : document.getElementById('replay-badge').textContent,
              done: !!window.berthing.frame
                    && Math.abs(window.berthing.frame.t - {QUAY_TIME_S}) < 0.15}})""")
            if seen["badge"]:
                badges.add(seen["badge"])
            if seen["done"]:
                break
            time.sleep(0.05)
        took = time.monotonic() - tic
        seeking = sorted(b for b in badges if b.startswith("SEEKING TO 1:00.0 — "))
        assert seeking or took < 3.0, (took, badges)
        assert all(b.endswith(" %") for b in seeking), seeking
        f = wait_frame(pg, f"f => Math.abs(f.t - {QUAY_TIME_S}) < 0.15", timeout_s=30)
        print(f"seek 0 → {QUAY_TIME_S:g} s took {took:.1f} s ({seeking[-1:]})")
        assert pg.evaluate("() => window.berthing.session.state") == "paused"
        _wait(pg, "b.trust.trusted", 5)
        seen = quay_foot_clicks(rec, f["gpst"])
        assert seen is not None, "the quay foot is not in view"
        clicks, true_bow = seen
        assert 10.0 <= true_bow <= 20.0
        tolerance = max(0.15, 0.01 * true_bow)
        berth = _click_berth(pg, clicks)["overlay"]["berth"]
        assert berth["method"] == "quay-face", berth
        bow = berth["bow_distance_m"]
        assert bow == pytest.approx(true_bow, abs=tolerance)
        assert berth["bow_distance_sigma_m"] < 0.3
        assert "quay face" in pg.locator("#berth-method").inner_text()
        # the angle to the berth and the time to contact carry their σ too
        angle = pg.locator("#angle").inner_text()
        assert re.search(r"±\d+(\.\d)?°", angle), angle
        if berth["time_to_contact_s"] is not None:
            assert "±" in pg.locator("#ttc").inner_text()
        shot(pg, "11_berth_true_quay_foot")
        print(f"bow {bow:.3f} m ±{berth['bow_distance_sigma_m']:.3f}, true {true_bow:.3f} m")
        for du, dv in ((0, 3), (3, -3)):
            slipped = _click_berth(pg, clicks + [du, dv])["overlay"]["berth"]
            print(f"slip ({du}, {dv}) px: bow {slipped['bow_distance_m']:.3f} m")
            assert slipped["method"] == "quay-face"
            assert slipped["bow_distance_m"] == pytest.approx(true_bow, abs=tolerance)
            assert abs(slipped["bow_distance_m"] - bow) <= 0.3
        # nudged by hand: the figures follow, and the line says it is no longer the fit alone
        before = frame(pg)["overlay"]["berth"]["bow_distance_m"]
        pg.click("#nudge-out")
        pg.click("#nudge-out")
        nudged = wait_frame(pg, "f => f.overlay.berth && f.overlay.berth.nudged_m > 0.19")
        assert nudged["overlay"]["berth"]["bow_distance_m"] == pytest.approx(before + 0.2,
                                                                              abs=0.02)
        _wait(pg, "document.getElementById('berth-method').textContent.includes('nudged')", 5)
        assert "0.20 m out" in pg.locator("#berth-method").inner_text()
    finally:
        _close(pg, default_server)
