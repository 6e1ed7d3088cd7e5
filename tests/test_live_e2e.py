"""Live end to end: ``berthing-aid emulate`` plays the 12 s simulated recording on loopback as
the devices speak (four UBX TCP streams, the text IMU over UDP, an HTTP MJPEG camera);
``berthing-aid serve --live`` runs the engine on them. Checked: the live fused trajectory
matches a replay of the same recording on the same server; the page streams the live session
with its record indicator; the bridge NMEA (UDP IEC 61162-450 and TCP) parses with
pynmeagps and agrees with the trajectory; the recording written live loads and replays.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import socket
import subprocess
import sys
import time
import urllib.request
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from pynmeagps import NMEAReader

from estimator.frames import ecef_to_ned, geodetic_to_ecef, gpst_from_datetime

ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = ROOT / "tests" / "artifacts"
CHROMIUM = Path("/usr/bin/chromium")

pytestmark = pytest.mark.slow


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=10) as res:
        return res.read()


def _post(url: str, body: dict) -> dict:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as res:
        return json.loads(res.read())


def _trajectory(base: str, session: str) -> dict[str, np.ndarray]:
    text = _get(f"{base}/api/sessions/{session}/trajectory?format=csv").decode()
    rows = [line.split(",") for line in text.strip().splitlines()]
    head, body = rows[0], rows[1:]
    cols = {h: np.array([float(r[i]) for r in body]) for i, h in enumerate(head)
            if h != "phase"}
    cols["phase"] = np.array([r[head.index("phase")] for r in body])
    return cols


def _ned(traj: dict[str, np.ndarray], origin: np.ndarray) -> np.ndarray:
    return np.array([ecef_to_ned(geodetic_to_ecef(math.radians(a), math.radians(b), h), origin)
                     for a, b, h in zip(traj["lat_deg"], traj["lon_deg"], traj["height"],
                                        strict=True)])


def _sentences(data: bytes) -> list:
    return [msg for _raw, msg in NMEAReader(io.BytesIO(data), quitonerror=2) if msg is not None]


@pytest.fixture(scope="module")
def live_run(sim_recording: Path, tmp_path_factory: pytest.TempPathFactory):
    """Emulator + ``serve --live`` until the recording has played out; yields what was seen."""
    work = tmp_path_factory.mktemp("live")
    ARTIFACTS.mkdir(exist_ok=True)
    config = work / "live.toml"
    udp_port, tcp_port, port = _free_port(socket.SOCK_DGRAM), _free_port(), _free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OPENBLAS_NUM_THREADS": "1"}
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", udp_port))
    udp.settimeout(0.05)
    procs, page = [], None
    with (ARTIFACTS / "live-emulator.log").open("w") as emu_log, \
            (ARTIFACTS / "live-server.log").open("w") as srv_log:
        emu = subprocess.Popen(
            [sys.executable, "-m", "backend.cli", "emulate", str(sim_recording),
             "--write-config", str(config), "--record-dir", str(work / "recorded"),
             "--bridge-udp", f"127.0.0.1:{udp_port}", "--bridge-tcp", f"127.0.0.1:{tcp_port}"],
            cwd=ROOT, stdout=emu_log, stderr=subprocess.STDOUT, env=env)
        procs.append(emu)
        try:
            deadline = time.monotonic() + 60
            while not config.exists():
                assert emu.poll() is None, (ARTIFACTS / "live-emulator.log").read_text()
                assert time.monotonic() < deadline, "the emulator wrote no config"
                time.sleep(0.2)
            time.sleep(0.5)  # the file is complete
            srv = subprocess.Popen(
                [sys.executable, "-m", "backend.cli", "serve", str(sim_recording), "--live",
                 str(config), "--port", str(port), "--no-viewer", "--heading-alert-limit", "3"],
                cwd=ROOT, stdout=srv_log, stderr=subprocess.STDOUT, env=env)
            procs.append(srv)
            base = f"http://127.0.0.1:{port}"
            while True:
                assert srv.poll() is None, (ARTIFACTS / "live-server.log").read_text()
                with contextlib.suppress(OSError):
                    _get(base + "/openapi.json")
                    break
                assert time.monotonic() < deadline + 60, "the server did not answer"
                time.sleep(0.3)
            sessions = json.loads(_get(base + "/api/sessions"))["sessions"]
            live = next(s for s in sessions if s["live"] is not None)
            tcp = socket.create_connection(("127.0.0.1", tcp_port), timeout=5)
            tcp.settimeout(0.05)
            datagrams, stream = [], bytearray()
            if CHROMIUM.exists():
                page = _open_page(base)
            frames_seen, caught_up = [], ""
            # until the emulator has played the recording and the session has caught up
            progress = (-1, time.monotonic())
            while emu.poll() is None or time.monotonic() - progress[1] < 2.0:
                if emu.poll() is not None:  # played out: wait for the session to catch up
                    st = json.loads(_get(f"{base}/api/sessions/{live['id']}"))
                    n = st["frames_processed"]
                    camera = next(i for i in st["live"]["inputs"] if i["name"] == "camera")
                    # a frame is processed, dropped late, or skipped by an engine behind
                    skipped = st["live"]["skipped_frames"]
                    if n != progress[0] or n + skipped < camera["received"] - camera["late"]:
                        progress = (n, time.monotonic())
                    caught_up = f"frames processed {n}, skipped {skipped}, camera {camera}"
                with contextlib.suppress(TimeoutError):
                    datagrams.append(udp.recv(2048))
                with contextlib.suppress(TimeoutError):
                    stream += tcp.recv(65536)
                if page is not None and len(frames_seen) < 40:
                    frames_seen.append(page[1].evaluate(
                        "() => ({f: window.berthing.frame?.frame ?? null, "
                        "rec: document.querySelector('#st-rec').hidden ? null : "
                        "document.querySelector('#st-rec').textContent, "
                        "replay: !document.querySelector('#play').hidden "
                        "|| !document.querySelector('#seek').hidden})"))
                assert time.monotonic() < deadline + 120, \
                f"the live run did not end ({caught_up or 'the emulator still playing'})"
            status = json.loads(_get(f"{base}/api/sessions/{live['id']}"))
            # every sensor is silent now: the session must come to say so by itself
            quiet_deadline = time.monotonic() + 3.0
            while True:
                quiet = json.loads(_get(f"{base}/api/sessions/{live['id']}"))
                if quiet["fusion"]["integrity"]["mode"] == "no position" \
                        or time.monotonic() > quiet_deadline:
                    break
                time.sleep(0.1)
            live_traj = _trajectory(base, live["id"])
            replay = _post(base + "/api/sessions", {"recording": sim_recording.name,
                                                    "speed": "max"})
            while json.loads(_get(f"{base}/api/sessions/{replay['id']}"))["state"] != "ended":
                assert time.monotonic() < deadline + 240, "the replay did not end"
                time.sleep(0.5)
            replay_traj = _trajectory(base, replay["id"])
            header = None
            if page is not None:
                page[1].screenshot(path=str(ARTIFACTS / "live-page.png"))
                header = page[1].evaluate("""() => ({
                    width: document.documentElement.clientWidth,
                    night: document.querySelector('#theme').getBoundingClientRect().toJSON(),
                    chips: [...document.querySelectorAll('.status .chip')]
                        .filter((c) => !c.hidden)
                        .map((c) => ({text: c.textContent, rect: c.getBoundingClientRect().toJSON(),
                                      clipped: c.scrollWidth > c.clientWidth + 1}))})""")
        finally:
            if page is not None:  # else its Playwright loop outlives the fixture, and every
                page[0].close()  # later page test fails to start its own
            for p in reversed(procs):  # the server first: it closes the live recording
                p.terminate()
                try:
                    p.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    p.kill()
            udp.close()
    yield {"status": status, "quiet": quiet, "live": live_traj, "replay": replay_traj,
           "udp": datagrams, "tcp": bytes(stream), "frames_seen": frames_seen, "work": work,
           "header": header,
           "recording": sim_recording}


def _open_page(base: str):
    from playwright.sync_api import sync_playwright

    pw = sync_playwright().start()
    browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox",
                                                                       "--disable-gpu"])
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(base + "/")  # no ?session: the page opens the live session itself

    class Closer:
        def close(self) -> None:
            browser.close()
            pw.stop()

    return Closer(), page


def test_live_trajectory_matches_the_replay(live_run):
    live, replay = live_run["live"], live_run["replay"]
    from recordings.format import load

    rec = load(live_run["recording"], load_gnss=False)
    origin = rec.manifest.origin_llh
    fused = live["phase"] == "fused"
    # (an engine slower than real time skips frames: fewer on a loaded machine than 121)
    assert fused.sum() > 25, f"the live session fused {fused.sum()} frames"
    # The trajectory is the engine's (world frame: the body origin at the start, carrier-phase
    # integrated); its absolute anchor (standalone GNSS, metre-level) is compared separately.
    p_live = np.column_stack([live["north"], live["east"]])
    p_replay = np.column_stack([replay["north"], replay["east"]])
    # the replay's pose at each live frame time (frames 0.1 s apart, ~1 m/s: interpolated)
    at = np.column_stack([np.interp(live["gpst"], replay["gpst"], p_replay[:, k])
                          for k in range(2)])
    common = fused & (live["gpst"] >= replay["gpst"][replay["phase"] == "fused"][0])
    diff = np.linalg.norm((p_live - at)[common], axis=1)
    anchor = np.linalg.norm(_ned(live, origin)[common, :2] - np.column_stack(
        [np.interp(live["gpst"], replay["gpst"], _ned(replay, origin)[:, k])
         for k in range(2)])[common], axis=1)
    print(f"live vs replay, {common.sum()} fused frames: trajectory difference median "
          f"{np.median(diff) * 100:.2f} cm, max {diff.max() * 100:.2f} cm; absolute anchor "
          f"difference median {np.median(anchor):.3f} m")
    # within 2 cm; the odd frame beyond on a loaded machine (frames are timed on arrival, and a
    # busy CPU delays a few): 95 % within 2 cm, none beyond one frame's motion (0.1 s at the
    # recording's ~1 m/s: a clean-clone CI run had one frame 10 cm off, p95 0.08 cm)
    assert np.percentile(diff, 95) < 0.02 and diff.max() < 0.15
    assert np.median(anchor) < 1.0  # standalone-GNSS level
    status = live_run["status"]
    # every frame either processed or skipped by an engine behind the sensors (counted), or
    # still in the engine's queue (at most MAX_QUEUED_FRAMES)
    from backend.live_session import MAX_QUEUED_FRAMES

    seen = status["frames_processed"] + status["live"]["skipped_frames"] + MAX_QUEUED_FRAMES
    # a clean run: no input dropped a time tag ahead of the clock, nor had garbage rejected
    inputs = {i["name"]: i for i in status["live"]["inputs"]}
    assert all(i["ahead"] == 0 and i["rejected"] == 0 for i in inputs.values()), inputs
    assert seen >= 0.95 * len(rec.frame_times), json.dumps(
        {k: status[k] for k in ("state", "time_s", "frames_processed", "error", "live")})


def test_page_streams_the_live_session_with_the_record_indicator(live_run):
    seen = live_run["frames_seen"]
    if not seen:
        pytest.skip("no chromium at /usr/bin/chromium")
    frames = [s["f"] for s in seen if s["f"] is not None]
    assert len(set(frames)) >= 5, f"the page showed frames {frames}"
    assert any(s["rec"] and "REC" in s["rec"] for s in seen), seen[-3:]
    # a live session has nothing to play, pause or seek: no replay controls
    assert not any(s["replay"] for s in seen if s["f"] is not None), seen[-3:]
    # At the end every sensor is down and the record chip names them all: at 1280 px each
    # chip is whole and readable, none under the Night button or another chip (it ran under
    # the button, the failed inputs cut off).
    header = live_run["header"]
    rec = [c for c in header["chips"] if "REC" in c["text"]]
    assert rec and "down" in rec[0]["text"], header["chips"]
    night = header["night"]
    for k, chip in enumerate(header["chips"]):
        r = chip["rect"]
        assert not chip["clipped"] and 0 <= r["left"] and r["right"] <= header["width"], chip
        assert r["right"] <= night["left"] or r["top"] >= night["bottom"], (chip, night)
        for other in header["chips"][k + 1:]:
            o = other["rect"]
            apart = (r["right"] <= o["left"] or o["right"] <= r["left"]
                     or r["bottom"] <= o["top"] or o["bottom"] <= r["top"])
            assert apart, (chip, other)


def test_bridge_nmea_parses_and_agrees(live_run):
    datagrams = live_run["udp"]
    assert datagrams and all(d.startswith(b"UdPbC\x00") for d in datagrams)
    udp_sentences = []
    for d in datagrams:
        for part in d[6:].split(b"\\")[1:]:  # tag block, sentence, tag block, sentence…
            if part.startswith(b"$"):
                udp_sentences += _sentences(part)
    tcp_sentences = _sentences(live_run["tcp"])
    for sentences in (udp_sentences, tcp_sentences):
        kinds = {m.msgID for m in sentences}
        assert {"HDT", "THS", "ROT", "VTG", "GGA", "ZDA"} <= kinds, kinds
    live = live_run["live"]
    fused = live["phase"] == "fused"
    gga = [m for m in udp_sentences if m.msgID == "GGA" and m.quality == 1]
    assert gga, "no GGA with a trusted position"
    # Each update's heading is the ship's at the time its GGA gives (the state carried from
    # its frame to the sending, ``bridge_state``): against the recording's truth there. Its
    # position is the session's own fused track at that time (compared with the nearest
    # state of the track, the last GGA was up to 1 s ahead of it: 0.5 m at 1 m/s).
    from recordings.format import load

    ref = load(live_run["recording"], load_gnss=False).reference
    track_t = live["gpst"][fused]
    errors, position_off = [], []
    for d in datagrams:
        got = {}
        for part in d[6:].split(b"\\")[1:]:
            if part.startswith(b"$"):
                got.update({m.msgID: m for m in _sentences(part)})
        hdt, gga, zda = got.get("HDT"), got.get("GGA"), got.get("ZDA")
        if hdt is None or gga is None or zda is None or hdt.headingT == "" or gga.quality != 1:
            continue
        g = gga.time
        utc = datetime(int(zda.year), int(zda.month), int(zda.day), g.hour, g.minute, g.second,
                       g.microsecond)
        t = gpst_from_datetime(utc) + 18.0  # UTC to GPS time: the bridge's leap seconds
        yaw = math.degrees(float(ref.interpolate(np.array([t]))[2][0, 2]))
        if math.isfinite(yaw):  # (the last may be after the recording's end)
            errors.append(abs((float(hdt.headingT) - yaw + 180) % 360 - 180))
        if track_t[0] <= t <= track_t[-1]:
            position_off.append(math.hypot(
                float(gga.lat) - np.interp(t, track_t, live["lat_deg"][fused]),
                float(gga.lon) - np.interp(t, track_t, live["lon_deg"][fused])))
    assert len(errors) >= 5, errors
    assert np.median(errors) < 0.3 and max(errors) < 1.0, errors
    assert len(position_off) >= 5 and max(position_off) < 2e-6, position_off


def test_recording_written_live_loads_and_replays(live_run):
    from engine.driver import create_engine, dispatch
    from engine.messages import sensor_messages
    from recordings.format import load

    (recorded,) = (live_run["work"] / "recorded").iterdir()
    rec = load(recorded)
    original = load(live_run["recording"], load_gnss=False)
    assert json.loads((recorded / "manifest.json").read_text())["live"]["complete"] is True
    assert len(rec.frame_times) >= 0.95 * len(original.frame_times)
    assert len(rec.imu.time) >= 0.99 * len(original.imu.time)
    assert all(len(e) >= 12 for e in rec.gnss)
    engine = create_engine(rec.calibration, rec.nav, {})
    states = [s for m in sensor_messages(rec) if (s := dispatch(engine, m)) is not None]
    assert states and states[-1].status.phase == "fused"
    live = live_run["live"]
    k = len(live["gpst"]) - 1
    last = min(states, key=lambda s: abs(float(s.time) - live["gpst"][k]))
    assert abs(float(last.time) - live["gpst"][k]) < 0.05
    d = np.array([live["north"][k], live["east"][k]]) - np.asarray(last.position_ned)[:2]
    assert np.linalg.norm(d) < 0.05, f"the recorded berthing replays {np.linalg.norm(d):.3f} m " \
                                     f"away from the live trajectory at {last.time}"


def test_example_config_is_valid(tmp_path: Path):
    """The commented example in the repository parses (with its files in place)."""
    from live.config import ConfigError, load_config

    text = (ROOT / "live" / "example.toml").read_text()
    (tmp_path / "calibration.json").write_text("{}")
    (tmp_path / "hull.json").write_text("{}")
    (tmp_path / "live.toml").write_text(text)
    cfg = load_config(tmp_path / "live.toml")
    assert cfg.imu.kind == "text" and len(cfg.receivers) == 4
    assert cfg.bridge.udp == ("239.192.0.2", 60002) and cfg.bridge.rates_hz["heading"] == 10
    (tmp_path / "live.toml").write_text(text.replace("latency_s", "latncy_s"))
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['latncy_s'\]"):
        load_config(tmp_path / "live.toml")


def test_an_engine_behind_the_sensors_skips_frames_never_imu_or_gnss():
    """Messages queued faster than the engine takes them: every IMU sample reaches the engine,
    video frames beyond MAX_QUEUED_FRAMES waiting are skipped (and counted), in time order."""
    from backend.live_session import MAX_QUEUED_FRAMES, LiveRunner
    from engine.messages import FrameMessage, ImuMessage

    class Source:
        nav = None

        def next(self, timeout):  # nothing more arrives
            return None

        def close(self):
            pass

    msgs = []
    for k in range(40):  # 4 s: 10 IMU samples and one frame per 0.1 s
        t = 100.0 + 0.1 * k
        msgs += [ImuMessage(t + 0.01 * j, np.zeros(3), np.zeros(3)) for j in range(6)]
        msgs.append(FrameMessage(t + 0.055, k, np.zeros((2, 2, 3), np.uint8)))
        msgs += [ImuMessage(t + 0.01 * j, np.zeros(3), np.zeros(3)) for j in range(6, 10)]
    runner = LiveRunner(Source(), None, None, None, None, msgs[0])
    for m in msgs[1:]:
        runner._queue.append(m)
        runner._queued_frames += isinstance(m, FrameMessage)
    taken = []
    while runner._queue:
        taken.append(runner._next_for_engine())
    imu = [m for m in taken if isinstance(m, ImuMessage)]
    frames = [m for m in taken if isinstance(m, FrameMessage)]
    assert len(imu) == 400
    assert len(frames) == MAX_QUEUED_FRAMES and runner.skipped_frames == 40 - MAX_QUEUED_FRAMES
    assert [f.index for f in frames] == list(range(40 - MAX_QUEUED_FRAMES, 40))  # the newest
    assert all(a.t <= b.t for a, b in zip(taken, taken[1:], strict=False))


def test_a_live_feed_gone_quiet_is_declared(live_run):
    """Once the emulator has played out, every sensor is silent. Nothing arrives to make
    the engine notice, so the live session tells it the time: the session declares no
    position (untrusted, the IMU's silence first) rather than keep its last fused status."""
    fusion = live_run["quiet"]["fusion"]  # within 3 s of the session having caught up
    integrity = fusion["integrity"]
    assert integrity["mode"] == "no position" and not integrity["trusted"], fusion
    assert "no IMU sample" in integrity["reasons"][0], integrity["reasons"]
    assert fusion["phase"] == "degraded"


def test_a_live_camera_gone_silent_leaves_no_stale_pose(sim_recording: Path):
    """The camera stops while the IMU and the receivers go on: the pose, the alarms and the
    berth figures go on from the fusion's state between frames, which says the video is lost —
    not the last frame's pose, trusted and "tracking" (a user trial: a 6 s camera outage,
    /pose 7 s old)."""
    import copy
    from types import SimpleNamespace

    from backend.catalog import RecordingCatalog
    from backend.errors import Conflict
    from backend.live_session import LiveRunner
    from backend.models import FusionOptionsModel, StreamFrameHeader
    from backend.sessions import SessionManager
    from engine.driver import create_engine
    from engine.messages import FrameMessage, sensor_messages
    from recordings.format import load

    rec = load(sim_recording)
    start = rec.manifest.start_gpst
    cut, end = start + 6.0, start + 10.0
    messages = [m for m in sensor_messages(rec, until=end)
                if not (isinstance(m, FrameMessage) and m.t > cut)]

    class Source:  # the recording's sensors, the camera silent after ``cut``
        nav = rec.nav
        health = list
        # no wall clock to tie to GNSS time: no quiet ticks, no lag (as fast as it goes)
        aligner = SimpleNamespace(clock=SimpleNamespace(to_gpst=lambda _wall: None))

        def __init__(self) -> None:
            self.left = iter(messages[1:])

        def next(self, timeout):
            msg = next(self.left, None)
            if msg is None:
                time.sleep(timeout)  # every sensor silent (no quiet tick: no clock here)
            return msg

        def close(self):
            pass

    live_rec = copy.copy(rec)  # the runner lists the frames it got in its recording
    manager = SessionManager(RecordingCatalog(None, sim_recording), create_engine)
    heard: list[float] = []  # what a frame listener (the bridge, the 3-D view) is told

    def listen(session, result):
        heard.append(result.t)
        assert result.state is not None and result.live

    manager.created_listeners.append(lambda s: s.frame_listeners.append(listen))
    sent: list[dict] = []  # what the page is sent

    class Page:
        def offer(self, header: bytes, jpeg: bytes | None) -> None:
            if jpeg is not None:  # a frame (its header without the sender's closing fields)
                sent.append(json.loads(header + b',"seq":0,"sent_at":0}'))

        def end(self, reason: str) -> None:
            pass

    manager.created_listeners.append(lambda s: s.subscribe(Page()))
    session = manager.add(live_rec, "live-test", lambda make_engine, s: LiveRunner(
        Source(), make_engine, s, live_rec, None, messages[0]),
        FusionOptionsModel().model_dump())
    try:
        deadline = time.monotonic() + 120
        while session.replayer.status()["time_gpst"] < messages[-1].t - 1e-6:
            assert time.monotonic() < deadline, session.replayer.status()
            time.sleep(0.2)
        state = session.current_state()
        assert state.time > end - 0.6, state.time - start  # not the last frame's (6 s)
        status = state.status
        assert status.vo_status == "lost", status
        assert any("no video frame" in r for r in status.integrity.reasons), status.integrity
        assert session.report()["samples"] > 0
        assert max(heard) > end - 0.6  # the bridge's heading goes on without the camera
        # the page gets its last picture again with the state now: status, alarms, panels;
        # nothing drawn on the picture, and it is said how old it is
        later = [h for h in sent if h["gpst"] > cut + 1.0]
        assert later and all(h["picture_t"] is not None for h in later)
        last = later[-1]
        StreamFrameHeader.model_validate(last)
        assert last["gpst"] > end - 0.6 and last["picture_t"] <= cut - start + 1e-6
        assert last["status"]["vo_status"] == "lost" and last["pose"] is not None
        assert not last["overlay"]["video"]["grid"]["lines"]
        assert not last["overlay"]["video"]["points"]["uv"]
        assert all(h["picture_t"] is None for h in sent if h["gpst"] <= cut + 1e-6)
        # a click now would be on the last picture, 4 s old, with the present pose: refused
        with pytest.raises(Conflict, match="no picture at"):
            session.designate(None, 400.0, 300.0, None)
    finally:
        manager.close_all()
