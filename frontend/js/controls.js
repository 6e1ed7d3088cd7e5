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
    this.playing = !!s.playing;
    this.play.textContent = this.playing ? "❚❚" : "▶";
    this.play.title = this.playing ? "Pause (space)" : "Play (space)";
    this.seek.max = String(s.duration_s);
    this.duration.textContent = fmtTime(s.duration_s);
    if (s.speed != null && [...this.speed.options].some((o) => o.value === String(s.speed))) {
      this.speed.value = String(s.speed);
    }
    if (!this.dragging && s.state !== "playing") this.setTime(s.seek_target_s ?? s.time_s);
    const badge = {
      paused: "PAUSED", ended: "END OF RECORDING",
      // what stopped it stays on screen (the toast goes): ▶ restarts the replay
      error: `REPLAY STOPPED: ${(s.error || "unknown error").slice(0, 140)} — ▶ restarts it`,
      seeking: `SEEKING ${fmtTime(s.seek_target_s)}…`, starting: "STARTING…",
    }[s.state];
    this.badge.hidden = !badge;
    this.badge.textContent = badge || "";
  }

  /** From each shown frame: the time of the picture on screen. */
  setTime(t) {
    if (this.dragging) return;
    this.seek.value = String(t);
    this.time.textContent = fmtTime(t);
  }
}
