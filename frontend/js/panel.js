// The berthing panel: what pilots' docking displays give. Bow and stern distance to the berth
// line (from the hull's foremost and aftmost points) with their σ, approach speeds in cm/s
// coloured by the session's approach alarms (amber, red: the limits depend on the distance,
// see the limits table), speed along the berth, angle to it, time to contact; and the ship's
// heading, speed over ground and rate of turn. The alarms themselves are the server's (one
// alarm list with the integrity alarms): the panel only shows their level where the figure is.

import { fmtDistance } from "./format.js";

const KNOTS_PER_MPS = 3600 / 1852;

function fmtSigma(s) {
  return s == null ? "" : `±${s.toFixed(s < 0.095 ? 2 : 1)}`;
}

/** " ±0.3°", or nothing below ``min`` (a σ under the digit shown says nothing). */
function fmtSigmaDeg(s, min = 0) {
  return s == null || s < min ? "" : ` ±${s.toFixed(s < 0.95 ? 1 : 0)}°`;
}

/** A speed's σ in cm/s, " ±24", once it reaches the digit shown (0.5 cm/s). */
function fmtSigmaCms(mps) {
  const cms = (mps ?? 0) * 100;
  return cms >= 0.5 ? ` ±${cms.toFixed(0)}` : "";
}

function fmtSigmaTime(s) {
  if (s == null) return "";
  return s >= 60 ? ` ±${(s / 60).toFixed(1)} min` : ` ±${s.toFixed(s < 9.5 ? 1 : 0)} s`;
}

const METHOD_TEXT = {
  "quay-face": (b) => `quay face · ${b.support_points} pts · σ ${b.sigma_m?.toFixed(2) ?? "–"} m`,
  "water-plane": () => "water plane: no quay points near the clicks",
};
const SOURCE_TEXT = { recording: "from the recording", ned: "from the plan", typed: "typed in", image: "from the video" };

export class Panel {
  constructor(root) {
    this.el = (id) => root.querySelector(`#${id}`);
    this.card = this.el("berth");
    this.level = null;
  }

  /** ``noData``: nothing new from the server (the figures are left out, and said why).
   *  @returns {null | "warning" | "alarm"} the approach alarm level shown (none on an
   *  untrusted pose: the figures are then greyed, see status.js) */
  update(frame, trusted = true, noData = false) {
    this.trusted = trusted;
    const pose = frame?.pose;
    const berth = frame?.overlay?.berth;
    this._nav(pose);
    this.card.classList.toggle("unset", !berth);
    const levels = {};
    for (const a of frame?.alarms || []) {
      if (a.kind.startsWith("approach-")) levels[a.kind.slice(9)] = a.severity;
    }
    const bow = this._end("bow", berth, trusted ? levels.bow : null);
    const stern = this._end("stern", berth, trusted ? levels.stern : null);
    this._more(berth, noData ? "no new data" : frame?.status && !pose ? "no position" : "no line");
    this.level = [bow, stern].includes("alarm") ? "alarm" : [bow, stern].includes("warning") ? "warning" : null;
    return this.level;
  }

  _end(name, berth, level) {
    const d = this.el(`${name}-dist`);
    const s = this.el(`${name}-speed`);
    const distance = berth?.[`${name}_distance_m`];
    const sigma = berth?.[`${name}_distance_sigma_m`];
    d.innerHTML = distance == null ? "–"
      : `${fmtDistance(distance)}<span class="unit">m</span><span class="dir">${fmtSigma(sigma)}</span>`;
    const approach = berth?.[`${name}_approach_mps`];
    s.classList.toggle("alarm", level === "alarm");
    s.classList.toggle("warning", level === "warning");
    if (approach == null) {
      s.innerHTML = "–";
      s.title = "";
      return null;
    }
    const cms = approach * 100;
    // positive = closing the berth; the arrow says which way without reading a sign
    const arrow = Math.abs(cms) < 0.5 ? "" : cms > 0 ? "▼" : "▲";
    const dir = Math.abs(cms) < 0.5 ? "steady" : cms > 0 ? "closing" : "opening";
    // its σ once it reaches the figure's last digit (the carrier phase holds it to mm/s;
    // an INS fault found widens it to decimetres a second)
    const pm = fmtSigmaCms(berth?.[`${name}_approach_sigma_mps`]);
    // (the σ on the direction's line: beside the figure it pushed the stern's column off a
    // 1400 px screen, a user trial)
    s.innerHTML = `${arrow}${Math.abs(cms).toFixed(0)}<span class="unit">cm/s</span>`
      + `<span class="dir">${dir}${pm}</span>`;
    s.title = cms > 0 ? "closing the berth line" : "opening from the berth line";
    return level || null;
  }

  _more(berth, why) {
    const set = (id, html) => { this.el(id).innerHTML = html; };
    if (!berth) {
      for (const id of ["along", "angle", "ttc"]) set(id, "–");
      this.el("berth-method").textContent = why;
      return;
    }
    const along = berth.along_berth_mps;
    set("along", along == null ? "–" : `${Math.abs(along * 100).toFixed(0)}<span class="unit">cm/s ${along >= 0 ? "fwd" : "aft"}${fmtSigmaCms(berth.along_berth_sigma_mps)}</span>`);
    const angle = berth.angle_deg;
    const angleSigma = fmtSigmaDeg(berth.angle_sigma_deg);
    set("angle", angle == null ? "–" : `${Math.abs(angle).toFixed(1)}<span class="unit">° ${Math.abs(angle) < 0.5 ? "" : angle > 0 ? "bow in" : "stern in"}${angleSigma}</span>`);
    const ttc = berth.time_to_contact_s;
    const ttcSigma = fmtSigmaTime(berth.time_to_contact_sigma_s);
    set("ttc", ttc == null ? "none" : ttc >= 600 ? "&gt;10<span class=\"unit\">min</span>"
      : ttc >= 60 ? `${Math.floor(ttc / 60)}:${String(Math.round(ttc % 60)).padStart(2, "0")}<span class="unit">min${ttcSigma}</span>`
        : `${ttc.toFixed(0)}<span class="unit">s${ttcSigma}</span>`);
    const info = this.el("berth-method");
    const how = METHOD_TEXT[berth.method]?.(berth) ?? SOURCE_TEXT[berth.source] ?? "";
    // moved by hand since it was set: the figures are to the officer's line, not the fit's
    const parts = [];
    if (Math.abs(berth.nudged_m ?? 0) >= 0.005) parts.push(`${Math.abs(berth.nudged_m).toFixed(2)} m ${berth.nudged_m > 0 ? "out" : "in"}`);
    if (Math.abs(berth.nudged_deg ?? 0) >= 0.05) parts.push(`${berth.nudged_deg.toFixed(1)}°`);
    info.textContent = parts.length ? `${how} · nudged ${parts.join(", ")}` : how;
    info.title = berth.note || "";
    info.classList.toggle("warn", berth.method === "water-plane");
  }

  _nav(pose) {
    const set = (id, html) => { this.el(id).innerHTML = html; };
    if (!pose) {
      for (const id of ["hdg", "sog", "rot", "cog"]) set(id, "–");
      return;
    }
    // σ of heading and course once they reach the digit shown (a slow ship's course is
    // degrees off: ±σ says so)
    set("hdg", `${pose.heading_deg.toFixed(1)}<span class="unit">°${fmtSigmaDeg(pose.heading_std_deg, 0.05)}</span>`);
    set("sog", `${(pose.speed_mps * KNOTS_PER_MPS).toFixed(2)}<span class="unit">kn</span>`
      + ` <span class="unit sub">${pose.speed_mps.toFixed(2)}${pose.speed_std_mps >= 0.005
        ? ` ±${pose.speed_std_mps.toFixed(2)}` : ""} m/s</span>`);
    // ROT in degrees per minute, as on a ship's ROT indicator; positive = to starboard
    const rot = pose.rate_of_turn_dps * 60;
    const side = Math.abs(rot) < 0.5 ? "" : rot > 0 ? " S" : " P";
    // its σ once it matters (a gyro fault: the bias widened to the step, ±30°/min)
    const rotSigma = (pose.rate_of_turn_std_dps ?? 0) * 60;
    set("rot", `${Math.abs(rot).toFixed(0)}<span class="unit">°/min${side}`
      + `${rotSigma >= 1 ? ` ±${rotSigma.toFixed(0)}` : ""}</span>`);
    set("cog", pose.course_deg == null ? "–" : `${pose.course_deg.toFixed(1)}<span class="unit">°${fmtSigmaDeg(pose.course_std_deg, 0.05)}</span>`);
  }
}

/** The approach-limit table editor (rows of the session's ApproachLimits). */
export class Limits {
  constructor(root, { load, save }) {
    this.body = root.querySelector("#limits-body");
    this.now = root.querySelector("#limit-now");
    this.rows = [];
    this.load = load;
    root.querySelector("#limits-save").addEventListener("click", async () => {
      const rows = [...this.body.querySelectorAll("tr")].map((tr) => {
        const [w, a, r] = [...tr.querySelectorAll("input")].map((i) => parseFloat(i.value));
        return { within_m: w, warning_cms: a, alarm_cms: r };
      }).filter((r) => Number.isFinite(r.within_m) && r.within_m > 0);
      const out = await save({ rows });
      if (out) { this.show(out.rows); this.update(this.berth); }
    });
  }

  async refresh() {
    const out = await this.load();
    if (out) this.show(out.rows);
  }

  show(rows) {
    this.rows = rows;
    // one spare empty row to add a band
    const all = [...rows, { within_m: "", warning_cms: "", alarm_cms: "" }];
    this.body.replaceChildren(...all.map((r) => {
      const tr = document.createElement("tr");
      for (const key of ["within_m", "warning_cms", "alarm_cms"]) {
        const td = document.createElement("td");
        const input = Object.assign(document.createElement("input"), {
          type: "number", min: "0", step: "any", value: String(r[key]),
        });
        input.dataset.key = key;
        td.append(input);
        tr.append(td);
      }
      return tr;
    }));
  }

  /** The limits that apply at the ship's present distance, next to the table's title. */
  update(berth) {
    this.berth = berth;
    const d = berth ? Math.min(berth.bow_distance_m ?? Infinity, berth.stern_distance_m ?? Infinity) : Infinity;
    const row = this.rows.filter((r) => d < r.within_m).sort((a, b) => a.within_m - b.within_m)[0];
    this.now.textContent = !berth ? "" : row
      ? `— now ${row.warning_cms.toFixed(0)}/${row.alarm_cms.toFixed(0)} cm/s (within ${row.within_m} m)`
      : "— none at this distance";
  }
}
