// The per-session WebSocket: a text header per frame followed by the frame's JPEG (binary),
// plus status messages. Newest frame wins: while one JPEG is being decoded, later arrivals
// replace each other and only the newest is decoded next, so the display never lags behind.
// Rendering happens on the next animation frame with the header of THAT frame, which keeps
// the overlay exactly in step with the picture.

import { accessToken } from "./api.js";

const RECONNECT_MS = [500, 1000, 2000, 4000, 5000];
// No frame for this long while playing: say so (and the page stops trusting what it shows).
// Three frame intervals of a 10 fps video at the replay's speed, at least a second.
const STALE_MIN_MS = 1000;
const staleMs = (speed) => (typeof speed === "number" && speed > 0
  ? Math.max(STALE_MIN_MS, 300 / speed) : STALE_MIN_MS);
// A frame shown this much later than frames can be (its server time against the best
// transport seen): the page itself is behind (a starved browser showed data 8 s old, no
// warning, in a user trial); back below half of it.
const BEHIND_S = 1.5;
const BEST_OF_FRAMES = 300; // the best transport over this many frames (clock offset + delay)

export class Stream {
  /**
   * @param {object} handlers  onFrame(header, bitmap), onStatus(session), onState(state, detail),
   *                           onGone(detail) when the session no longer exists.
   */
  constructor(handlers) {
    this.h = handlers;
    this.ws = null;
    this.sessionId = null;
    this.state = "idle"; // idle | connecting | live | stale | behind | reconnecting | closed
    this.attempt = 0;
    this.header = null; // header waiting for its JPEG
    this.next = null; // newest undecoded {header, blob}
    this.decoding = false;
    this.ready = null; // decoded, waiting for the animation frame
    this.lastFrameAt = 0;
    this.playing = false;
    this.frames = 0;
    this.dropped = 0;
    this._timer = null;
    this.staleMs = STALE_MIN_MS;
    this.transport = []; // receipt − sent_at (s, browser − server clock) of recent frames
    this.behindS = 0; // how much later than the best case the last frame was shown
    this._stale = setInterval(() => this._checkStale(), 250);
  }

  open(sessionId) {
    this.close();
    this.sessionId = sessionId;
    this.attempt = 0;
    this._connect();
  }

  close() {
    clearTimeout(this._timer);
    if (this.ws) {
      this.ws.onclose = null;
      this.ws.close();
      this.ws = null;
    }
    this.sessionId = null;
    this.header = this.next = null;
    this._set("idle");
  }

  _connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const token = accessToken();
    const query = token ? `?token=${encodeURIComponent(token)}` : "";
    const ws = new WebSocket(`${proto}//${location.host}/api/sessions/${this.sessionId}/stream${query}`);
    ws.binaryType = "blob";
    this.ws = ws;
    this._set(this.attempt ? "reconnecting" : "connecting");
    ws.onopen = () => { this.attempt = 0; this._set("live"); };
    ws.onmessage = (ev) => this._message(ev.data);
    ws.onclose = (ev) => {
      this.ws = null;
      if (ev.code === 4404) { // the server says the session is gone
        this._set("closed", "session gone");
        this.h.onGone?.("the session no longer exists");
        return;
      }
      if (ev.code === 4401) { // no valid access token: retrying will not help
        this._set("closed", "access token needed");
        return;
      }
      const delay = RECONNECT_MS[Math.min(this.attempt, RECONNECT_MS.length - 1)];
      this.attempt += 1;
      this._set("reconnecting", `retry in ${(delay / 1000).toFixed(1)} s`);
      this._timer = setTimeout(() => this._connect(), delay);
    };
  }

  _message(data) {
    if (typeof data !== "string") { // the JPEG of the header just received
      if (!this.header) return;
      if (this.next) this.dropped += 1;
      this.next = { header: this.header, blob: data };
      this.header = null;
      this._decode();
      return;
    }
    const msg = JSON.parse(data);
    if (msg.type === "frame") {
      this.header = msg;
      if (typeof msg.sent_at === "number") {
        this.transport.push(Date.now() / 1000 - msg.sent_at);
        if (this.transport.length > BEST_OF_FRAMES) this.transport.shift();
      }
    } else if (msg.type === "status") {
      // a seek sends no frame until it arrives (its progress is on the replay badge)
      this.playing = !!msg.session?.playing && msg.session.state !== "seeking";
      this.staleMs = staleMs(msg.session?.speed);
      this.h.onStatus?.(msg.session);
    } else if (msg.type === "closed" || msg.type === "error") {
      // "closed": the session was deleted; "error": it never existed
      this.ws && (this.ws.onclose = null);
      this._set("closed", msg.detail);
      this.h.onGone?.(msg.detail);
    }
  }

  async _decode() {
    if (this.decoding || !this.next) return;
    this.decoding = true;
    const { header, blob } = this.next;
    this.next = null;
    try {
      const bitmap = await createImageBitmap(blob);
      if (this.ready) { this.ready.bitmap.close?.(); this.dropped += 1; }
      this.ready = { header, bitmap };
      requestAnimationFrame(() => this._render());
    } catch (err) {
      console.warn("frame decode failed", err);
    }
    this.decoding = false;
    this._decode(); // a newer frame may have arrived meanwhile
  }

  _render() {
    if (!this.ready) return;
    const { header, bitmap } = this.ready;
    this.ready = null;
    this.frames += 1;
    this.lastFrameAt = performance.now();
    // (a paused replay's frame is of then by design: a new client gets it at once)
    this.behindS = this.playing && typeof header.processed_at === "number" && this.transport.length
      ? Date.now() / 1000 - header.processed_at - Math.min(...this.transport) : 0;
    if (this.behindS > BEHIND_S) this._set("behind", `${this.behindS.toFixed(1)} s behind`);
    else if (this.state === "stale" || (this.state === "behind" && this.behindS < BEHIND_S / 2)) {
      this._set("live");
    }
    this.h.onFrame(header, bitmap); // the handler owns the bitmap from here (keeps it for redraws)
  }

  _checkStale() {
    if (this.state === "live" && this.playing && this.lastFrameAt
        && performance.now() - this.lastFrameAt > this.staleMs) {
      this._set("stale", "no frames");
    }
  }

  _set(state, detail = "") {
    if (state === this.state && detail === this.detail) return;
    this.state = state;
    this.detail = detail;
    this.h.onState?.(state, detail);
  }
}
