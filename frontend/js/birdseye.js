// The bird's-eye (plan) view, drawn from the same stream message as the video so the two always
// show the same instant. Centred on the ship; north-up or head-up; range rings and a scale bar
// give distances at a glance; the same distance colours as on the video.

import { colors } from "./theme.js";
import { fmtMeasured } from "./format.js";
import { drawPick, label } from "./overlay.js";

const RANGES_M = [5, 10, 20, 30, 50, 100, 200, 500, 1000]; // half-width of the view
const MIN_SHIP_PX = 22;
const NICE = [1, 2, 5, 10, 20, 25, 50, 100, 200, 250, 500, 1000];

export class BirdsEye {
  constructor(canvas) {
    this.canvas = canvas;
    this.mode = localStorage.getItem("berthing.plan") || "north"; // "north" | "head"
    this.rangeIndex = null; // null: follow the server's grid radius until the user zooms
    this.frame = null;
    this.view = null;
  }

  setMode(mode) {
    this.mode = mode;
    localStorage.setItem("berthing.plan", mode);
    this.draw(this.frame, this.opts);
  }

  zoom(step) {
    const current = this.rangeIndex ?? this._autoIndex();
    this.rangeIndex = Math.min(Math.max(current + step, 0), RANGES_M.length - 1);
    this.draw(this.frame, this.opts);
  }

  /** Automatic range: the server's grid radius, widened to keep the berth line in view. */
  _autoIndex() {
    const plan = this.frame?.overlay?.birdseye;
    let need = plan?.radius_m ?? 30;
    if (plan?.berth_line) need = Math.max(need, 1.2 * segmentDistance(plan.position, plan.berth_line) + 8);
    let i = RANGES_M.findIndex((x) => x >= need);
    if (i < 0) i = RANGES_M.length - 1;
    // hysteresis: zoom out at once, zoom in only when clearly inside the smaller range, so the
    // scale does not flicker while the distance hovers at a step
    if (this._auto != null && i < this._auto && need > 0.8 * RANGES_M[i]) i = this._auto;
    this._auto = i;
    return i;
  }

  /** Rotation of the plan on screen: 0 north-up, the ship's heading head-up (rad). */
  _rotation() {
    return this.mode === "head" ? ((this.frame?.overlay?.birdseye?.heading_deg ?? 0) * Math.PI) / 180 : 0;
  }

  /** Plan (north, east) → CSS px on the canvas. */
  toScreen([n, e]) {
    const v = this.view;
    const dn = n - v.centre[0];
    const de = e - v.centre[1];
    const c = Math.cos(v.rot), s = Math.sin(v.rot);
    const fwd = dn * c + de * s; // along the screen's up direction
    const right = -dn * s + de * c;
    return [v.cx + right * v.ppm, v.cy - fwd * v.ppm];
  }

  /** CSS px → plan (north, east). */
  toPlan(x, y) {
    const v = this.view;
    if (!v) return null;
    const right = (x - v.cx) / v.ppm;
    const fwd = (v.cy - y) / v.ppm;
    const c = Math.cos(v.rot), s = Math.sin(v.rot);
    return [v.centre[0] + fwd * c - right * s, v.centre[1] + fwd * s + right * c];
  }

  /**
   * @param {object} frame  stream header (frame.overlay.birdseye is the plan content)
   * @param {object} opts   {predictSeconds, trusted, picks: [[n,e]...] pending berth clicks}
   */
  draw(frame, opts = {}) {
    this.frame = frame;
    this.opts = opts;
    const canvas = this.canvas;
    const c = colors();
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = c.planBg;
    ctx.fillRect(0, 0, w, h);
    const plan = frame?.overlay?.birdseye;
    if (!plan) {
      // a status without a pose: the fusion had one and lost it (no IMU)
      label(ctx, 12, 20, frame?.status ? "no position" : "no position yet", c.planText,
        "transparent", 14);
      this.view = null;
      return;
    }
    const range = RANGES_M[this.rangeIndex ?? this._autoIndex()];
    this.view = {
      centre: plan.position, rot: this._rotation(), cx: w / 2, cy: h / 2,
      ppm: Math.min(w, h) / 2 / range,
    };
    if (!opts.trusted) ctx.filter = "grayscale(1)";

    const step = niceStep(range / 2);
    this._rings(ctx, step, range, c);
    this._polygon(ctx, plan.frustum, null, c.frustum);
    this._points(ctx, plan.points, c, opts.allPoints);
    if (plan.berth_line) this._berth(ctx, plan.berth_line, c);
    this._prediction(ctx, plan.prediction, opts.predictSeconds ?? 99, c);
    // the ship last: nothing may hide it
    this._polygon(ctx, this._shipOutline(plan), c.shipEdge, c.ship, 1.5);
    this._heading(ctx, plan, range, c);
    ctx.filter = "none";
    // labels never overlap one another nor the own ship: each takes the first free place
    // around its mark, or is left out (the mark stays; the list has the figure)
    const ship = this._shipOutline(plan).map((p) => this.toScreen(p));
    const xs = ship.map((p) => p[0]), ys = ship.map((p) => p[1]);
    this.placed = [[Math.min(...xs) - 4, Math.min(...ys) - 4, Math.max(...xs) + 4, Math.max(...ys) + 4]];
    for (const t of plan.targets || []) this._target(ctx, t, frame.overlay.targets, c);
    for (const p of opts.picks || []) drawPick(ctx, this.toScreen(p), c, 7);
    this._north(ctx, w, c);
    this._scaleBar(ctx, step, h, c);
    label(ctx, w - 86, h - 16, this.mode === "head" ? "HEAD-UP" : "NORTH-UP", c.planText,
      "transparent", 12);
  }

  /** The hull to scale, or enlarged about the ship's reference point when it would be smaller
   *  than a symbol one can see (as ECDIS does for its own-ship symbol). */
  _shipOutline(plan) {
    const [n0, e0] = plan.position;
    const length = Math.sqrt(Math.max(...plan.ship.map((p) => dist2(p, plan.position)))) * 2;
    const k = Math.max(1, MIN_SHIP_PX / (length * this.view.ppm));
    return plan.ship.map(([n, e]) => [n0 + k * (n - n0), e0 + k * (e - e0)]);
  }

  _rings(ctx, step, range, c) {
    const v = this.view;
    ctx.strokeStyle = c.planGrid;
    ctx.lineWidth = 1;
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillStyle = c.planText;
    ctx.globalAlpha = 0.9;
    for (let r = step; r <= range * 1.5; r += step) {
      ctx.beginPath();
      ctx.arc(v.cx, v.cy, r * v.ppm, 0, 2 * Math.PI);
      ctx.stroke();
      const x = v.cx + r * v.ppm * 0.707 + 3, y = v.cy - r * v.ppm * 0.707 - 3;
      if (x < 2 * v.cx - 34 && y > 14) { // only labels that fit on the canvas
        ctx.globalAlpha = 0.55;
        ctx.fillText(`${r} m`, x, y);
        ctx.globalAlpha = 0.9;
      }
    }
    ctx.globalAlpha = 1;
  }

  _path(ctx, pts, close = true) {
    ctx.beginPath();
    pts.forEach((p, i) => {
      const [x, y] = this.toScreen(p);
      if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    if (close) ctx.closePath();
  }

  _polygon(ctx, pts, stroke, fill, width = 1) {
    if (!pts?.length) return;
    this._path(ctx, pts);
    if (fill) { ctx.fillStyle = fill; ctx.fill(); }
    if (stroke) { ctx.strokeStyle = stroke; ctx.lineWidth = width; ctx.stroke(); }
  }

  _points(ctx, points, c, all) {
    if (!points?.ne?.length) return;
    ctx.globalAlpha = c.pointAlpha;
    for (let i = 0; i < points.ne.length; i++) {
      const obstacle = points.obstacle ? points.obstacle[i] : points.converged?.[i] !== false;
      if (!obstacle && !all) continue;
      const [x, y] = this.toScreen(points.ne[i]);
      if (!obstacle) { // not an obstacle (converging, on the water, far): a faint hollow mark
        ctx.strokeStyle = c.other;
        ctx.lineWidth = 1;
        ctx.strokeRect(x - 1.5, y - 1.5, 3, 3);
        continue;
      }
      ctx.fillStyle = c.bands[points.band?.[i] ?? 6] || points.color[i];
      ctx.fillRect(x - 1.8, y - 1.8, 3.6, 3.6);
    }
    ctx.globalAlpha = 1;
  }

  _prediction(ctx, prediction, maxSeconds, c) {
    const shown = (prediction || []).filter((p) => p.seconds <= maxSeconds);
    const n = shown.length;
    ctx.strokeStyle = c.predict;
    shown.forEach((p, i) => {
      ctx.globalAlpha = n > 1 ? 1 - 0.7 * (i / (n - 1)) : 1;
      ctx.lineWidth = 1.8;
      this._path(ctx, p.ne);
      ctx.stroke();
    });
    ctx.globalAlpha = 1;
  }

  _heading(ctx, plan, range, c) {
    // dashed heading line from the bow: where the ship points, not where it goes
    const bow = plan.ship.reduce((a, b) => (dist2(b, plan.position) > dist2(a, plan.position) ? b : a));
    const psi = (plan.heading_deg * Math.PI) / 180;
    const far = [plan.position[0] + Math.cos(psi) * range * 2, plan.position[1] + Math.sin(psi) * range * 2];
    const [x0, y0] = this.toScreen(bow);
    const [x1, y1] = this.toScreen(far);
    ctx.strokeStyle = c.ship;
    ctx.globalAlpha = 0.6;
    ctx.setLineDash([6, 5]);
    ctx.lineWidth = 1.2;
    ctx.beginPath();
    ctx.moveTo(x0, y0);
    ctx.lineTo(x1, y1);
    ctx.stroke();
    ctx.setLineDash([]);
    ctx.globalAlpha = 1;
  }

  _berth(ctx, line, c) {
    ctx.strokeStyle = c.berth;
    ctx.lineWidth = 3.5;
    this._path(ctx, line, false);
    ctx.stroke();
  }

  _target(ctx, t, readouts, c) {
    const [x, y] = this.toScreen(t.ne);
    ctx.strokeStyle = c.target;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.arc(x, y, 6, 0, 2 * Math.PI);
    ctx.stroke();
    const r = readouts?.find((o) => o.id === t.id);
    const text = r ? `${r.label || t.id} ${fmtMeasured(r.distance_m, r.distance_sigma_m)}` : t.id;
    ctx.font = "700 12px system-ui, sans-serif";
    const w = ctx.measureText(text).width + 8, h = 20;
    for (const [dx, dy] of [[9, -10], [9, 10], [-9 - w, -10], [-9 - w, 10], [-w / 2, -22], [-w / 2, 22]]) {
      const box = [x + dx - 4, y + dy - h / 2, x + dx - 4 + w, y + dy + h / 2];
      if (this.placed.some((p) => box[0] < p[2] && box[2] > p[0] && box[1] < p[3] && box[3] > p[1])) continue;
      this.placed.push(box);
      label(ctx, x + dx, y + dy, text, c.target, c.targetBg, 12);
      return;
    }
  }

  _north(ctx, w, c) {
    // north arrow, top right; turns with the plan in head-up, its "N" stays upright
    const x = w - 24, y = 30, r = 13;
    const a = -this.view.rot;
    ctx.save();
    ctx.translate(x, y);
    ctx.rotate(a);
    ctx.fillStyle = c.planText;
    ctx.beginPath();
    ctx.moveTo(0, -r); ctx.lineTo(5, 5); ctx.lineTo(0, 2); ctx.lineTo(-5, 5);
    ctx.closePath();
    ctx.fill();
    ctx.restore();
    ctx.font = "700 11px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    ctx.fillStyle = c.planText;
    ctx.fillText("N", x + Math.sin(a) * (r + 8), y - Math.cos(a) * (r + 8));
    ctx.textAlign = "start";
  }

  _scaleBar(ctx, step, h, c) {
    const len = step * this.view.ppm;
    const x = 12, y = h - 14;
    ctx.strokeStyle = c.planText;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + len, y); ctx.lineTo(x + len, y - 5);
    ctx.stroke();
    ctx.fillStyle = c.planText;
    ctx.font = "700 12px system-ui, sans-serif";
    ctx.fillText(`${step} m`, x + len + 6, y - 1);
  }
}

function niceStep(x) {
  return NICE.reduce((best, s) => (Math.abs(s - x) < Math.abs(best - x) ? s : best), NICE[0]);
}

/** Distance (m) from a plan point to a segment [a, b]. */
function segmentDistance(p, [a, b]) {
  const dn = b[0] - a[0], de = b[1] - a[1];
  const t = Math.max(0, Math.min(1, ((p[0] - a[0]) * dn + (p[1] - a[1]) * de) / (dn * dn + de * de || 1)));
  return Math.hypot(p[0] - a[0] - t * dn, p[1] - a[1] - t * de);
}

function dist2(a, b) {
  return (a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2;
}
