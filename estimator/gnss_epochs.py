"""GNSS epoch intake of the fusion: the four receivers' epochs of one time tag, the satellites
the experiment keeps (thesis tables 18–21, sky mask), the standalone position ``r`` and the
geometry of the epoch; the previous epoch is kept for the time differences (TDCP)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .cpp import EpochGeometry, epoch_geometry
from .frames import SPEED_OF_LIGHT
from .integrity import IntegrityMonitor
from .options import FusionOptions
from .records import GnssEpoch, NavigationData
from .spp import standalone_position

N_RECEIVERS = 4
SPP_EXPECTED_SATELLITES = 6  # with this many, a failed standalone solution is a fault


class GnssFront:
    """Epoch selection, SPP and geometry; ``prev`` / ``prev_geo`` are the last epoch used."""

    def __init__(self, nav: NavigationData, options: FusionOptions,
                 monitor: IntegrityMonitor | None = None) -> None:
        self.nav = nav
        self.options = options
        self.monitor = monitor
        self.t_first: float | None = None  # gpst of the first epoch seen
        self.prev: list[GnssEpoch | None] = [None] * N_RECEIVERS
        self.prev_geo: EpochGeometry | None = None
        self.spp_ecef: np.ndarray | None = None
        self.spp_covariance: np.ndarray | None = None  # ECEF m² (``StandalonePosition``)
        self.clock_bias_s = 0.0

    def select(self, t: float, epochs: Sequence[GnssEpoch | None], carrier_off: bool
               ) -> list[GnssEpoch | None]:
        """The satellite-blocking scenarios of the thesis (tables 18–21): after
        ``keep_after_s`` only the kept satellites; ``carrier_off``: none at all (INS runs)."""
        opt = self.options
        epochs = list(epochs) + [None] * (N_RECEIVERS - len(epochs))
        if self.t_first is None:
            self.t_first = t
        late = t - self.t_first >= opt.keep_after_s
        out: list[GnssEpoch | None] = []
        for i, ep in enumerate(epochs[:N_RECEIVERS]):
            if ep is None:
                out.append(None)
                continue
            keep = set(ep.satellites)
            if late and opt.satellites_keep is not None:
                keep &= set(opt.satellites_keep)
            if late and opt.per_receiver_sats is not None and i in opt.per_receiver_sats:
                keep &= set(opt.per_receiver_sats[i])
            if carrier_off:
                keep = set()
            if keep != set(ep.satellites):
                ep = GnssEpoch(ep.time, {s: o for s, o in ep.satellites.items() if s in keep},
                               ep.flag)
            out.append(ep)
        return out

    def geometry(self, t: float, epochs: Sequence[GnssEpoch | None],
                 receiver_ecef: np.ndarray) -> EpochGeometry:
        sats = sorted({s for e in epochs if e is not None for s in e.satellites})
        return epoch_geometry(self.nav, sats, t, receiver_ecef, self.clock_bias_s,
                              self.options.elevation_mask_deg)

    def standalone(self, epochs: Sequence[GnssEpoch | None], joint: bool) -> None:
        """Standalone position (``joint``: over all receivers, before the INS runs; else one
        receiver is enough: it only anchors llh and gives the receiver clock bias)."""
        present = [e for e in epochs if e is not None and e.satellites]
        if not present:
            self.spp_ecef = self.spp_covariance = None
            return
        if not joint:
            present = present[:1]
        spp = standalone_position(present, self.nav,
                                  elevation_mask_deg=self.options.elevation_mask_deg,
                                  initial_ecef=self.spp_ecef)
        t = present[0].time
        if spp is not None and (self.monitor is None or self.monitor.spp(t, spp.position)):
            self.spp_ecef, self.spp_covariance = spp.position, spp.covariance
            self.clock_bias_s = spp.clock_bias_m / SPEED_OF_LIGHT
            return
        self.spp_ecef = self.spp_covariance = None
        tracked = len(present[0].satellites)
        if spp is None and self.monitor is not None and tracked >= SPP_EXPECTED_SATELLITES:
            self.monitor.raise_fault("spp-implausible", t, f"no plausible standalone position "
                                     f"from {tracked} satellites: absolute position held")

    def advance(self, epochs: list[GnssEpoch | None], geo: EpochGeometry | None) -> None:
        """This epoch becomes the previous one."""
        self.prev, self.prev_geo = epochs, geo
