// The berthing panel: what crews actually call out. Bow and stern distance to the berth line,
// their approach speeds in cm/s (an alarm when closing faster than the limit), and the ship's
// heading, speed over ground and rate of turn.

const LIMIT_KEY = "berthing.limitCms";
const KNOTS_PER_MPS = 3600 / 1852;

export class Panel {
  constructor(root) {
    this.el = (id) => root.querySelector(`#${id}`);
    this.card = this.el("berth");
    this.limitInput = this.el("limit");
    this.limitInput.value = localStorage.getItem(LIMIT_KEY) || this.limitInput.value;
    this.limitInput.addEventListener("change", () => {
      localStorage.setItem(LIMIT_KEY, this.limitInput.value);
    });
    this.alarm = false;
  }

  get limitCms() {
    const v = parseFloat(this.limitInput.value);
    return Number.isFinite(v) && v > 0 ? v : 15;
  }

  /** @returns {boolean} whether an approach-speed alarm is on (never on an untrusted pose: the
   *  figures are then shown greyed, see status.js) */
  update(frame, trusted = true) {
    this.trusted = trusted;
    const pose = frame?.pose;
    const berth = frame?.overlay?.berth;
    this._nav(pose);
    this.card.classList.toggle("unset", !berth);
    const bow = this._end("bow", berth?.bow_distance_m, berth?.bow_approach_mps);
    const stern = this._end("stern", berth?.stern_distance_m, berth?.stern_approach_mps);
    this.alarm = bow || stern;
    return this.alarm;
  }

  _end(name, distance, approach) {
    const d = this.el(`${name}-dist`);
    const s = this.el(`${name}-speed`);
    d.innerHTML = distance == null ? "–" : `${distance.toFixed(2)}<span class="unit">m</span>`;
    if (approach == null) {
      s.innerHTML = "–";
      s.classList.remove("alarm");
      s.title = "";
      return false;
    }
    const cms = approach * 100;
    // positive = closing the berth; the arrow says which way without reading a sign
    const arrow = Math.abs(cms) < 0.5 ? "" : cms > 0 ? "▼" : "▲";
    const dir = Math.abs(cms) < 0.5 ? "steady" : cms > 0 ? "closing" : "opening";
    s.innerHTML = `${arrow}${Math.abs(cms).toFixed(0)}<span class="unit">cm/s</span>`
      + `<span class="dir">${dir}</span>`;
    s.title = cms > 0 ? "closing the berth line" : "opening from the berth line";
    const alarm = this.trusted && cms > this.limitCms;
    s.classList.toggle("alarm", alarm);
    return alarm;
  }

  _nav(pose) {
    const set = (id, html) => { this.el(id).innerHTML = html; };
    if (!pose) {
      for (const id of ["hdg", "sog", "rot", "cog"]) set(id, "–");
      return;
    }
    set("hdg", `${pose.heading_deg.toFixed(1)}<span class="unit">°</span>`);
    set("sog", `${(pose.speed_mps * KNOTS_PER_MPS).toFixed(2)}<span class="unit">kn</span>`
      + ` <span class="unit">${pose.speed_mps.toFixed(2)} m/s</span>`);
    // ROT in degrees per minute, as on a ship's ROT indicator; positive = to starboard
    const rot = pose.rate_of_turn_dps * 60;
    const side = Math.abs(rot) < 0.5 ? "" : rot > 0 ? " S" : " P";
    set("rot", `${Math.abs(rot).toFixed(0)}<span class="unit">°/min${side}</span>`);
    set("cog", pose.course_deg == null ? "–" : `${pose.course_deg.toFixed(1)}<span class="unit">°</span>`);
  }
}
