// The alarm list (integrity, faults and berthing approach speed from the server, each frame):
// an alarm of severity "alarm" (red) sounds (Web Audio, a two-tone beep every second) until it
// is acknowledged; a "warning" (amber) chimes once when it appears; an acknowledged alarm stays
// listed, silent, while it is active. Browsers only start audio after
// a user gesture: the sound starts on the first click or key anywhere on the page.

export class Alarms {
  constructor(root, acknowledge) {
    this.card = root.querySelector("#alarms");
    this.list = root.querySelector("#alarm-list");
    this.acknowledge = acknowledge; // (alarmId) => Promise
    this.current = [];
    this.shownKey = ""; // the list as drawn (see update)
    this.ctx = null;
    this.timer = null;
    this.sounding = false;
    this.beeps = 0; // for the tests: how many beeps were played
    this.chimes = 0; // and how many single chimes (new warnings)
    this.heard = new Set(); // warnings already chimed for
    root.querySelector("#alarm-ack-all").addEventListener("click", () => this.acknowledgeAll());
    const unlock = () => {
      if (!this.ctx && (window.AudioContext || window.webkitAudioContext)) {
        this.ctx = new (window.AudioContext || window.webkitAudioContext)();
      }
      this.ctx?.resume?.();
    };
    window.addEventListener("pointerdown", unlock, { capture: true });
    window.addEventListener("keydown", unlock, { capture: true });
  }

  /** The active alarms of a frame header. */
  update(alarms) {
    this.current = alarms || [];
    this.card.hidden = this.current.length === 0;
    for (const a of this.current) {
      if (a.severity === "warning" && !a.acknowledged && !this.heard.has(a.id)) {
        this.heard.add(a.id);
        this._chime();
      }
    }
    // Rebuilt only when the list changes: a button re-created every frame could not be clicked
    // (a message whose figures change is updated in place)
    const key = JSON.stringify(this.current.map((a) => [a.id, a.severity, a.acknowledged, a.repeats]));
    if (key !== this.shownKey) {
      this.shownKey = key;
      this.list.replaceChildren(...this.current.map((a) => this._item(a)));
    } else {
      this.current.forEach((a, i) => {
        const text = this.list.children[i]?.querySelector(".alarm-text");
        if (text && text.textContent !== a.message) text.textContent = a.message;
      });
    }
    this._sound(this.current.some((a) => a.severity === "alarm" && !a.acknowledged));
  }

  async acknowledgeAll() {
    const open = this.current.filter((a) => !a.acknowledged);
    for (const a of open) a.acknowledged = true; // silent at once, whatever the network does
    this.update(this.current);
    await Promise.allSettled(open.map((a) => this.acknowledge(a.id)));
  }

  _item(a) {
    const li = document.createElement("li");
    li.className = `alarm ${a.severity}${a.acknowledged ? " acked" : ""}`;
    li.dataset.id = a.id;
    li.dataset.kind = a.kind;
    const text = document.createElement("span");
    text.className = "alarm-text";
    text.textContent = a.message;
    const since = document.createElement("span");
    since.className = "alarm-since muted small";
    // back within seconds of clearing: the same alarm, counted (not a new one sounding)
    since.textContent = `${a.since_s.toFixed(1)} s${a.repeats ? ` · ${a.repeats + 1}×` : ""}`;
    if (a.first_message && a.first_message !== a.message) li.title = `first: ${a.first_message}`;
    li.append(text, since);
    if (!a.acknowledged && a.severity === "alarm") {
      const b = document.createElement("button");
      b.className = "btn btn-small";
      b.textContent = "Ack";
      b.addEventListener("click", async () => {
        a.acknowledged = true;
        this.update(this.current);
        await this.acknowledge(a.id).catch(() => {});
      });
      li.append(b);
    }
    return li;
  }

  _sound(on) {
    this.sounding = on;
    if (on && !this.timer) {
      this._beep();
      this.timer = setInterval(() => this._beep(), 1000);
    } else if (!on && this.timer) {
      clearInterval(this.timer);
      this.timer = null;
    }
  }

  _chime() {
    this.chimes += 1;
    this._tones([[740, 0]]);
  }

  _beep() {
    this.beeps += 1;
    this._tones([[880, 0], [660, 0.18]]);
  }

  _tones(tones) {
    const ctx = this.ctx;
    if (!ctx || ctx.state !== "running") return;
    const t = ctx.currentTime;
    for (const [freq, at] of tones) {
      const osc = ctx.createOscillator();
      const gain = ctx.createGain();
      osc.frequency.value = freq;
      gain.gain.setValueAtTime(0.0001, t + at);
      gain.gain.exponentialRampToValueAtTime(0.2, t + at + 0.02);
      gain.gain.exponentialRampToValueAtTime(0.0001, t + at + 0.16);
      osc.connect(gain).connect(ctx.destination);
      osc.start(t + at);
      osc.stop(t + at + 0.17);
    }
  }
}
