"""The live merge (``live.source.TimeAligner``) under the faults a user trial found: a time
tag ahead of the clock, a device that comes back after stopping, a stream the merge waits for.

Driven in real time (two seconds a test): IMU samples every 10 ms and the receivers' epochs
every 100 ms, tagged on a GNSS time that runs with the host's monotonic clock."""

from __future__ import annotations

import time

import numpy as np
import pytest

from engine.messages import FrameMessage, GnssMessage, ImuMessage
from estimator.records import GnssEpoch
from live.source import TimeAligner

G0 = 1_400_000_000.0


class Feed:
    """Sensors in real time: IMU and camera every 10 / 100 ms, epochs every 100 ms."""

    def __init__(self, aligner: TimeAligner) -> None:
        self.a = aligner
        self.m0 = time.monotonic()
        self.out: list = []

    def gpst(self) -> float:
        return G0 + time.monotonic() - self.m0

    def run(self, seconds: float, epoch_tag=None, camera: bool = False,
            skip: tuple[str, float, float] | None = None) -> None:
        """``epoch_tag(rx, k, t)``: the time tag receiver ``rx`` gives epoch ``k`` of grid time
        ``t`` (default t); ``skip``: (stream, from, to) s of the run the stream is silent."""
        start = time.monotonic() - self.m0
        k0 = int(start / 0.01) + 1  # after the last run's
        for k in range(k0, k0 + int(round(seconds / 0.01))):
            wake = self.m0 + 0.01 * k
            while time.monotonic() < wake:
                time.sleep(0.001)
            t = G0 + 0.01 * k

            def silent(stream: str, k: int = k) -> bool:
                return skip is not None and skip[0] == stream and \
                    skip[1] <= 0.01 * k - start < skip[2]

            if not silent("imu"):
                self.a.put("imu", ImuMessage(t, np.zeros(3), np.zeros(3)))
            if k % 10 == 0:
                for rx in ("rx1", "rx2"):
                    if not silent(rx):
                        tag = t if epoch_tag is None else epoch_tag(rx, k, t)
                        self.a.put(rx, GnssEpoch(tag, {}))
                if camera and not silent("camera"):
                    # timed on the host clock, 20 ms after the IMU sample of its time
                    time.sleep(0.002)
                    self.a.put("camera", FrameMessage(t - G0 + self.m0, k, np.zeros((2, 2, 3),
                                                                                     np.uint8)))
            while (msg := self.a.next(0.0)) is not None:
                self.out.append(msg)

    def released(self, kind: type) -> list:
        return [m for m in self.out if isinstance(m, kind)]


@pytest.mark.parametrize("ahead_s", [3600.0, 2.0])
def test_one_receivers_epoch_tagged_ahead_is_dropped_and_the_merge_goes_on(ahead_s: float):
    """A receiver tags one epoch ``ahead_s`` too late (a valid checksum, every other sensor
    right). Let in, it moved the clock and the merge that far on: every later message of
    every sensor was late (the trial's session had no position for 17 s to an hour). Now it
    is dropped and counted on its input, and nothing else is lost."""
    feed = Feed(TimeAligner(receivers=2, max_lag_s=0.3))
    feed.run(2.0, epoch_tag=lambda rx, k, t: t + ahead_s if (rx, k) == ("rx2", 100) else t)
    imu = feed.released(ImuMessage)
    gnss = feed.released(GnssMessage)
    assert imu[-1].t - G0 > 1.6 and len(imu) >= 160, (len(imu), imu[-1].t - G0)
    assert all(m.t - G0 <= 2.0 + 1e-6 for m in feed.out)
    h = feed.a.health
    assert h["rx2"].ahead == 1 and "ahead" in (h["rx2"].error or "") and h["rx2"].late == 0
    assert h["imu"].late == 0 and h["rx1"].late == 0
    # the bad epoch's group is released without rx2; the later ones with both
    after = [m for m in gnss if m.t - G0 > 1.05]
    assert after and all(None not in m.epochs for m in after), after
    assert abs(feed.a.clock.offset - (G0 - feed.m0)) < 0.05


def test_an_imu_sample_tagged_ahead_does_not_drop_the_ones_after_it():
    """One IMU line 2 s ahead made the merge drop the next 200 good samples as late."""
    a = TimeAligner(receivers=2, max_lag_s=0.3)
    feed = Feed(a)
    feed.run(1.0)
    a.put("imu", ImuMessage(feed.gpst() + 2.0, np.zeros(3), np.zeros(3)))
    feed.run(1.0)
    assert a.health["imu"].ahead == 1 and a.health["imu"].late == 0
    assert len(feed.released(ImuMessage)) >= 160


def test_a_device_back_after_stopping_is_waited_for_again():
    """A camera that stopped and reconnected was never waited for again: its frames, a few
    ms behind the IMU as always, were dropped as late for the rest of the run (18 % of a
    trial's frames)."""
    a = TimeAligner(receivers=2, max_lag_s=0.3)
    feed = Feed(a)
    feed.run(0.6, camera=True)
    a.set_state("camera", "stopped", "stalled")
    feed.run(0.3, camera=True, skip=("camera", 0.0, 0.3))
    late = a.health["camera"].late
    feed.run(1.0, camera=True)
    assert "camera" not in a.stopped and a.health["camera"].state == "streaming"
    assert a.health["camera"].late == late, "frames dropped after the camera came back"
    assert a.health["camera"].error is None


def test_the_merge_says_from_when_it_holds_messages_back():
    """While one receiver is silent the merge holds the others' messages back for up to
    ``max_lag_s``: ``waiting_from`` says from when, so that the session does not declare
    the sensors it holds silent (the trial's "no IMU sample" for a stalled receiver)."""
    a = TimeAligner(receivers=2, max_lag_s=0.3)
    feed = Feed(a)
    feed.run(1.0)  # (at the start it waits for the camera, which never speaks, 0.6 s)
    assert a.waiting_from is None or a.waiting_from > feed.gpst() - 0.05
    seen = []
    orig = a._release

    def spy(now: float):
        out = orig(now)
        if out[0] is None and a.waiting_from is not None:
            seen.append(feed.gpst() - a.waiting_from)
        return out

    a._release = spy  # type: ignore[method-assign]
    feed.run(0.5, skip=("rx2", 0.0, 0.5))
    assert seen and 0.05 < max(seen) < 0.5, seen


def test_the_first_epoch_tagged_ahead_does_not_set_the_clock():
    """Receiver 1's very first epoch is tagged an hour ahead and the others come a little
    later (as when one receiver is up first): the clock, from that epoch alone, ran an hour
    on and the session never had a position (a second user trial). The clock now waits for
    three epochs' median, and judges the first ones by it."""
    a = TimeAligner(receivers=2, max_lag_s=0.3)
    feed = Feed(a)
    feed.run(2.0, epoch_tag=lambda rx, k, t: t + 3600.0 if (rx, k) == ("rx1", 10) else t)
    h = a.health
    assert h["rx1"].ahead == 1 and h["rx1"].late == 0 and h["rx2"].late == 0
    assert h["imu"].late == 0 and len(feed.released(ImuMessage)) >= 180
    gnss = feed.released(GnssMessage)
    assert all(m.t - G0 < 2.5 for m in gnss) and len(gnss) >= 15
    assert abs(a.clock.offset - (G0 - feed.m0)) < 0.05


def test_an_inputs_rejections_survive_its_reconnection():
    """What a receiver's decoder rejected is kept when the link is reopened (a new decoder):
    a second user trial saw 7 rejections on an input, then 0 a second later."""
    from types import SimpleNamespace

    from live.source import LiveSource

    config = SimpleNamespace(receivers=["tcp://a", "tcp://b"], max_lag_s=0.5,
                             camera=SimpleNamespace(latency_s=0.0))
    src = LiveSource(config)  # type: ignore[arg-type]
    src._decoder("rx1", SimpleNamespace(rejected_total=7, last_rejection="rx1: checksum"))
    src._decoder("rx1", SimpleNamespace(rejected_total=2, last_rejection=None))
    rx1 = next(h for h in src.health() if h["name"] == "rx1")
    assert rx1["rejected"] == 9 and rx1["last_rejection"] == "rx1: checksum"
