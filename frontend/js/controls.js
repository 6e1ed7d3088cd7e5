// Replay controls: play/pause, seek bar with time, speed and the recording picker. They send
// requests only; what is shown comes back from the session's status and frames.

export function fmtTime(s) {
  if (!Number.isFinite(s)) return "–";
  const m = Math.floor(s / 60);
  const sec = s - 60 * m;
  return `${m}:${sec.toFixed(1).padStart(4, "0")}`;
}

export class Controls {
  /** @param {object} on  play(), pause(), seek(t), speed(v), recording(name), predict(n) */
  constructor(root, on) {
    const $ = (id) => root.querySelector(`#${id}`);
    this.play = $("play");
    this.seek = $("seek");
    this.time = $("time");
    this.duration = $("duration");
    this.speed = $("speed");
    this.recording = $("recording");
    this.predict = $("predict");
    this.predictOut = $("predict-out");
    this.badge = $("replay-badge");
    this.playing = false;
    this.dragging = false;
    this.session = null;
    this.behind = 0;
    this.seekFrom = null;
    this.seekTarget = null;

    this.play.addEventListener("click", () => (this.playing ? on.pause() : on.play()));
    this.seek.addEventListener("input", () => {
      this.dragging = true;
      this.time.textContent = fmtTime(parseFloat(this.seek.value));
    });
    this.seek.addEventListener("change", () => {
      this.dragging = false;
      on.seek(parseFloat(this.seek.value));
    });
    this.speed.addEventListener("change", () => on.speed(this.speed.value));
    this.recording.addEventListener("change", () => on.recording(this.recording.value));
    this.predict.addEventListener("input", () => {
      this.predictOut.textContent = `${this.predict.value} s`;
      on.predict(parseInt(this.predict.value, 10));
    });
  }

  setRecordings(list, selected) {
    this.recording.replaceChildren(...list.map((r) => {
      const o = document.createElement("option");
      o.value = r.name;
      o.textContent = r.duration_s ? `${r.name} (${fmtTime(r.duration_s)})` : r.name;
      o.disabled = !!r.problem;
      return o;
    }));
    this.recording.value = selected;
  }

  setPredictMax(n) {
    this.predict.max = String(n);
    if (parseInt(this.predict.value, 10) > n) this.predict.value = String(n);
    this.predictOut.textContent = `${this.predict.value} s`;
  }

  get predictSeconds() {
    return parseInt(this.predict.value, 10);
  }

  /** From a session status (SessionStatus schema). */
  updateSession(s) {
    // a live session runs at the sensors' pace: nothing to play, pause, seek or speed up
    const live = !!s.live;
    for (const el of [this.play, this.seek, this.duration, this.speed.closest("label")]) {
      el.hidden = live;
    }
    this.playing = !!s.playing;
    this.play.textContent = this.playing ? "❚❚" : "▶";
    this.play.title = this.playing ? "Pause (space)" : "Play (space)";
    this.seek.max = String(s.duration_s);
    this.duration.textContent = fmtTime(s.duration_s);
    if (s.speed != null) {
      // a speed set elsewhere (the API, another screen) that the menu lacks is added to it:
      // the menu never shows a speed the replay is not running at
      const v = String(s.speed);
      if (![...this.speed.options].some((o) => o.value === v)) {
        this.speed.add(new Option(`${v}×`, v), this.speed.options[this.speed.options.length - 1]);
      }
      this.speed.value = v;
    }
    if (!this.dragging && s.state !== "playing" && s.state !== "seeking") this.setTime(s.time_s);
    if (s.state === "seeking") {
      // a backward seek restarts from a checkpoint: progress runs from the earliest time seen
      if (this.seekFrom == null || s.seek_target_s !== this.seekTarget) {
        this.seekFrom = s.time_s;
        this.seekTarget = s.seek_target_s;
      }
      this.seekFrom = Math.min(this.seekFrom, s.time_s);
    } else {
      this.seekFrom = this.seekTarget = null;
    }
    this.session = s;
    this.setScouted(s.scouted_s);
    this._badge();
  }

  /** From each shown frame: how the replay keeps up with real time. */
  setReplay(replay) {
    const playing = replay?.state === "playing";
    this.behind = playing ? replay.behind_s ?? 0 : 0;
    // what the replay achieves against the speed asked (an engine too slow for it)
    this.achieved = playing && replay.speed != null ? replay.achieved_speed ?? null : null;
    this.asked = replay?.speed ?? null;
    this.setScouted(replay?.scouted_s);
    this._badge();
  }

  /** The part of the seek bar a seek reaches quickly (the look-ahead engine has been there). */
  setScouted(scouted) {
    const max = parseFloat(this.seek.max) || 1;
    const pct = scouted == null ? 0 : Math.min(100, Math.max(0, (100 * scouted) / max));
    this.seek.style.setProperty("--ready", `${pct.toFixed(1)}%`);
    this.seek.title = scouted == null ? "Seek"
      : `Seek (quick up to ${fmtTime(scouted)}; beyond, the replay computes its way there)`;
  }

  _badge() {
    const s = this.session;
    if (!s) return;
    let text = {
      paused: "PAUSED", ended: "END OF RECORDING",
      // what stopped it stays on screen (the toast goes): ▶ restarts the replay
      error: `REPLAY STOPPED: ${(s.error || "unknown error").slice(0, 140)} — ▶ restarts it`,
      starting: "STARTING…",
    }[s.state];
    if (s.state === "seeking") {
      const span = (s.seek_target_s ?? 0) - (this.seekFrom ?? 0);
      const pct = span > 0 ? Math.min(99, Math.max(0, 100 * (s.time_s - this.seekFrom) / span)) : 0;
      text = `SEEKING TO ${fmtTime(s.seek_target_s)} — ${pct.toFixed(0)} %`;
      this.time.textContent = fmtTime(s.seek_target_s);
    } else if (s.state === "playing" && this.behind >= 1) {
      text = `BEHIND REAL TIME BY ${this.behind.toFixed(0)} s`;
      if (this.achieved != null && this.asked != null && this.achieved < 0.9 * this.asked) {
        text += ` — RUNNING AT ${this.achieved.toFixed(1)}× OF ${this.asked}×`;
      }
    }
    this.badge.hidden = !text;
    this.badge.textContent = text || "";
    this.badge.dataset.kind = s.state === "playing" ? "behind" : s.state;
  }

  /** From each shown frame: the time of the picture on screen. */
  setTime(t) {
    if (this.dragging) return;
    this.seek.value = String(t);
    this.time.textContent = fmtTime(t);
  }
}
