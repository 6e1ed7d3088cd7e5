// Fusion and connection status. Decides whether the overlay may be trusted: before the fusion
// runs on a fixed GNSS compass (phases initialising / aligning, compass float) the overlay is
// drawn in grey and a notice over the video says why. Degraded fusion and a provisional VO
// scale keep the colours but get an amber advisory: the picture is usable, with care.

// Connection states in which nothing new comes from the server: what is shown is of then.
export const NO_NEW_DATA = ["stale", "behind", "reconnecting", "closed"];

const CONN = {
  idle: ["–", "warn"],
  connecting: ["connecting", "warn"],
  live: ["live", "ok"],
  stale: ["no frames", "warn"],
  behind: ["behind", "bad"],
  reconnecting: ["reconnecting", "bad"],
  closed: ["closed", "bad"],
};

const PHASE_LEVEL = { fused: "ok", degraded: "warn", aligning: "bad", initialising: "bad" };

/** {trusted, reasons (grey-out), advisories} of a frame header. The engine's integrity
 *  (mode, protection levels, faults) decides; the phase only words it. Pure: tested through
 *  the page. */
export function assess(frame) {
  const st = frame?.status;
  const reasons = [];
  const advisories = [];
  if (!st) {
    reasons.push("Initialising — no fused position yet");
    return { trusted: false, reasons, advisories };
  }
  const ig = st.integrity;
  // a status without a pose: the fusion's last state is behind the frame (no IMU since)
  if (!frame.pose && !(ig && !ig.trusted)) reasons.push("No position — no fused pose for this frame");
  if (ig && !ig.trusted) {
    const mode = MODE_TEXT[ig.mode] || ig.mode;
    // no reason from the integrity (no position yet): the fusion's own words say why
    const why = ig.reasons[0] || (ig.mode === "no position" ? st.message : "");
    reasons.push(why ? `${mode} — ${why}` : mode);
    for (const r of ig.reasons.slice(1)) advisories.push(r);
  } else if (ig) {
    for (const r of ig.reasons) advisories.push(r); // warnings the fusion works around
  } else if (st.phase !== "fused" && st.phase !== "degraded") {
    reasons.push(`${st.phase} — ${st.message || "no trusted position"}`);
  }
  // the picture is an older one (a camera silent or frozen): the server drew nothing on it
  if (frame.picture_t != null) {
    reasons.push(`Camera picture ${Math.max(frame.t - frame.picture_t, 0).toFixed(1)} s old — nothing drawn on it`);
  }
  if (st.phase === "degraded") advisories.push("Coasting — no carrier-phase velocity, position drifting");
  if (st.vo_status === "lost") advisories.push("Visual odometry lost — 3-D points not updated");
  else if (st.vo_status === "excluded") {
    advisories.push("Visual odometry excluded (disagrees with the gyro or the GNSS track) — 3-D points not updated");
  }
  else if (st.vo_status === "tracking" && !st.scale_converged) {
    advisories.push("VO scale converging — point distances provisional");
  }
  return { trusted: reasons.length === 0, reasons, advisories };
}

const MODE_TEXT = {
  fused: "Fused",
  coasting: "Coasting (no carrier phase)",
  aligning: "Aligning — no GNSS compass fix",
  "no position": "No position",
};
const MODE_LEVEL = { fused: "ok", coasting: "warn", aligning: "bad", "no position": "bad" };

export class Status {
  constructor(root) {
    this.chip = (id) => root.querySelector(`#st-${id}`);
    this.notice = root.querySelector("#untrusted");
    this.connection = "idle";
    this.trust = { trusted: false, reasons: ["Waiting for the video stream"], advisories: [] };
  }

  /** Whether nothing new comes from the server (``NO_NEW_DATA``). */
  get noNewData() {
    return NO_NEW_DATA.includes(this.connection);
  }

  setConnection(state, detail) {
    this.connection = state;
    this.connectionDetail = detail;
    const [text, level] = CONN[state] || [state, "warn"];
    this._chip("conn", text, level, detail || "");
    this._notice();
  }

  /** Update from a frame header; returns {trusted, reasons, advisories}. */
  update(frame) {
    const st = frame?.status;
    this.trust = assess(frame);
    // no new frame for a while (or no connection): what is on screen is the past
    const frozen = this.noNewData;
    if (frozen) this.trust = { ...this.trust, trusted: false };
    if (!st) {
      for (const id of ["compass", "sats", "vo", "scale"]) this._chip(id, "–", "warn");
      this._chip("integrity", "no position", "bad");
      this._chip("phase", "initialising", "bad");
    } else {
      this._chip("phase", st.phase, PHASE_LEVEL[st.phase] || "warn", st.message);
      const ig = st.integrity;
      if (ig) {
        const pl = ig.hpl_m == null ? "" : ` ±${ig.hpl_m < 1 ? ig.hpl_m.toFixed(2) : ig.hpl_m.toFixed(1)} m`;
        this._chip("integrity", `${ig.mode}${pl}`, ig.trusted ? "ok" : MODE_LEVEL[ig.mode] === "warn" ? "warn" : "bad",
          `protection level ${ig.hpl_m ?? "–"} m (alert limit ${ig.alert_limit_m} m), heading `
          + `${ig.heading_pl_deg ?? "–"}° (alert limit ${ig.heading_alert_limit_deg}°)`
          + (ig.reasons.length ? `\n${ig.reasons.join("\n")}` : ""));
      } else {
        this._chip("integrity", "–", "warn");
      }
      this._chip("compass", st.compass_fixed ? "fixed" : "float", st.compass_fixed ? "ok" : "bad");
      // >= 4 satellites keep the carrier-phase velocity (thesis tables 18–19); fewer degrade it
      this._chip("sats", String(st.satellites), st.satellites >= 4 ? "ok" : st.satellites > 0 ? "warn" : "bad");
      this._chip("vo", st.vo_status, st.vo_status === "tracking" ? "ok" : st.vo_status === "lost" ? "bad" : "warn");
      this._chip("scale", st.scale_converged ? "converged" : "converging",
        st.scale_converged ? "ok" : "warn", st.scale == null ? "" : `VO scale ${st.scale.toFixed(3)}`);
    }
    if (frozen && st) {
      this._chip("integrity", "no data", "bad", "no new frame from the server");
      // what the others say is of then: not green (a user trial's FUSION "fused", COMPASS
      // "fixed" stayed green with the link lost)
      for (const id of ["phase", "compass", "sats", "vo", "scale"]) this.chip(id).dataset.level = "stale";
    }
    this._notice();
    return this.trust;
  }

  _notice() {
    const reasons = [...this.trust.reasons];
    if (this.connection === "reconnecting" || this.connection === "closed") {
      reasons.unshift("Connection lost — picture frozen");
    } else if (this.connection === "stale") {
      reasons.unshift("No new frames — picture frozen");
    } else if (this.connection === "behind") {
      reasons.unshift(`Display ${this.connectionDetail || "behind"} the sensors — figures withheld`);
    }
    const all = [...reasons, ...this.trust.advisories];
    this.notice.hidden = all.length === 0;
    this.notice.dataset.level = reasons.length ? "bad" : "warn";
    this.notice.textContent = reasons.length ? `Overlay not reliable: ${reasons[0]}` : all[0] || "";
    this.notice.title = all.join("\n");
  }

  _chip(id, text, level, title = "") {
    const el = this.chip(id);
    el.querySelector(".v").textContent = text;
    el.dataset.level = level;
    el.title = title;
  }
}
