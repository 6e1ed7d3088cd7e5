// Drawing of one video frame and its overlay. Everything on the video arrives already projected
// to image pixels for that very frame, so drawing is a scale + offset away: nothing here does
// geometry, which keeps the picture and the lines in step by construction.

import { fmtMeasured } from "./format.js";
import { colors } from "./theme.js";

/** Letterbox the source image (w x h px) into the canvas's CSS box; sizes the backing store for
 *  the device pixel ratio. Returns the image→CSS-pixel mapping shared by both canvases. */
export function fitCanvas(canvas, srcW, srcH) {
  const dpr = window.devicePixelRatio || 1;
  const cssW = canvas.clientWidth;
  const cssH = canvas.clientHeight;
  const pw = Math.max(1, Math.round(cssW * dpr));
  const ph = Math.max(1, Math.round(cssH * dpr));
  if (canvas.width !== pw || canvas.height !== ph) {
    canvas.width = pw;
    canvas.height = ph;
  }
  const scale = Math.min(cssW / srcW, cssH / srcH);
  return {
    dpr, scale, srcW, srcH,
    ox: (cssW - srcW * scale) / 2,
    oy: (cssH - srcH * scale) / 2,
  };
}

/** Image pixel (u, v) → CSS pixel in the canvas. */
export function toCss(view, u, v) {
  return [view.ox + u * view.scale, view.oy + v * view.scale];
}

/** CSS pixel in the canvas → image pixel, or null outside the picture. */
export function toImage(view, x, y) {
  const u = (x - view.ox) / view.scale;
  const v = (y - view.oy) / view.scale;
  if (u < 0 || v < 0 || u > view.srcW || v > view.srcH) return null;
  return [u, v];
}

export function drawVideo(canvas, bitmap, view) {
  const ctx = canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.setTransform(view.dpr, 0, 0, view.dpr, 0, 0);
  ctx.drawImage(bitmap, view.ox, view.oy, view.srcW * view.scale, view.srcH * view.scale);
}

/**
 * Overlay of one frame.
 * @param {object} frame   the stream header of the frame (frame.overlay may be null)
 * @param {object} opts    {predictSeconds, trusted, picks: [[u,v]...] pending berth clicks}
 */
export function drawOverlay(canvas, frame, view, opts) {
  const ctx = canvas.getContext("2d");
  const c = colors();
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const ov = frame?.overlay;
  if (!ov) return [];
  // image pixels → device pixels in one transform; line widths are divided by the scale so
  // they stay the same on screen whatever the window size.
  ctx.setTransform(view.dpr * view.scale, 0, 0, view.dpr * view.scale,
    view.dpr * view.ox, view.dpr * view.oy);
  const px = 1 / view.scale;
  ctx.save();
  ctx.beginPath();
  ctx.rect(0, 0, view.srcW, view.srcH);
  ctx.clip();

  // Untrusted fusion: the same drawing in grey, so nobody steers by it (status.js says why).
  if (!opts.trusted) ctx.filter = "grayscale(1)";

  drawGrid(ctx, ov.video.grid, opts.trusted ? c.grid : c.gridOff, px);
  drawPoints(ctx, ov.video.points, px, c, opts.allPoints);
  drawPrediction(ctx, ov.video.prediction, opts.predictSeconds, c, px);
  drawHull(ctx, ov.video.hull, c, px);
  if (ov.berth?.polylines) drawBerth(ctx, ov.berth.polylines, c, px);
  ctx.restore();

  // labels are drawn in CSS pixels so text is crisp and the same size at any window size;
  // the targets' distances last, on top of everything else
  ctx.setTransform(view.dpr, 0, 0, view.dpr, 0, 0);
  if (!opts.trusted) ctx.filter = "grayscale(1)";
  if (ov.berth?.polylines?.length) labelBerth(ctx, ov.berth, view, c);
  labelPrediction(ctx, ov.video.prediction, opts.predictSeconds, view, c);
  for (const p of opts.picks || []) drawPick(ctx, toCss(view, p[0], p[1]), c);
  const placed = []; // label boxes so far: targets close together keep readable labels
  for (const t of ov.targets || []) {
    if (t.visible && t.uv) {
      drawTarget(ctx, toCss(view, t.uv[0], t.uv[1]), t, c, opts.trusted,
        view.ox + view.srcW * view.scale, placed);
    }
  }
  ctx.filter = "none";
  return placed;
}

/** "N s" beside the bow of each predicted outline, skipping labels that would overlap. */
function labelPrediction(ctx, prediction, maxSeconds, view, c) {
  let last = null;
  for (const p of (prediction || []).filter((q) => q.seconds <= maxSeconds)) {
    const pts = p.polylines.flat();
    if (!pts.length) continue;
    const apex = pts.reduce((a, b) => (b[1] < a[1] ? b : a)); // the bow is the far (top) end
    const [x, y] = toCss(view, apex[0], apex[1]);
    if (last && Math.abs(y - last) < 16) continue;
    last = y;
    ctx.globalAlpha = 0.85;
    label(ctx, x + 8, y - 2, `${p.seconds} s`, c.predict, c.targetBg, 11);
    ctx.globalAlpha = 1;
  }
}

function strokePolylines(ctx, lines) {
  ctx.beginPath();
  for (const line of lines) {
    if (!line.length) continue;
    ctx.moveTo(line[0][0], line[0][1]);
    for (let i = 1; i < line.length; i++) ctx.lineTo(line[i][0], line[i][1]);
  }
  ctx.stroke();
}

function drawGrid(ctx, grid, color, px) {
  if (!grid?.lines?.length) return;
  ctx.strokeStyle = color;
  ctx.lineWidth = 1.6 * px;
  strokePolylines(ctx, grid.lines);
}

/** Structure points in the colour of their distance band. By default only the obstacles
 *  (converged, above the water, near the ship or the berth); with ``all`` the others too,
 *  as small hollow rings in a neutral colour. */
function drawPoints(ctx, points, px, c, all) {
  if (!points?.uv?.length) return;
  const r = 2.6 * px;
  ctx.globalAlpha = c.pointAlpha;
  for (let i = 0; i < points.uv.length; i++) {
    const obstacle = points.obstacle ? points.obstacle[i] : points.converged?.[i] !== false;
    if (!obstacle && !all) continue;
    const [u, v] = points.uv[i];
    ctx.beginPath();
    if (!obstacle) {
      ctx.arc(u, v, 0.7 * r, 0, 2 * Math.PI);
      ctx.strokeStyle = c.other;
      ctx.lineWidth = 1 * px;
      ctx.stroke();
      continue;
    }
    ctx.arc(u, v, r, 0, 2 * Math.PI);
    // a dark rim keeps yellow and cyan points visible on bright quay walls
    ctx.fillStyle = c.bands[points.band?.[i] ?? 6] || points.color[i];
    ctx.strokeStyle = "rgba(0,0,0,0.55)";
    ctx.lineWidth = 0.8 * px;
    ctx.fill();
    ctx.stroke();
  }
  ctx.globalAlpha = 1;
}

/** The hull now (0 s) at the water line: solid, the reference the predictions move from. */
function drawHull(ctx, lines, c, px) {
  if (!lines?.length) return;
  ctx.strokeStyle = c.hull;
  ctx.lineWidth = 3 * px;
  ctx.setLineDash([]);
  strokePolylines(ctx, lines);
}

/** Predicted outlines 1..N s ahead, fading with time: the nearest future is the surest. */
function drawPrediction(ctx, prediction, maxSeconds, c, px) {
  if (!prediction?.length) return;
  const shown = prediction.filter((p) => p.seconds <= maxSeconds);
  const n = shown.length;
  ctx.strokeStyle = c.predict;
  ctx.setLineDash([]);
  shown.forEach((p, i) => {
    ctx.globalAlpha = n > 1 ? 1 - 0.7 * (i / (n - 1)) : 1;
    ctx.lineWidth = (2.6 - 1.2 * (n > 1 ? i / (n - 1) : 0)) * px;
    strokePolylines(ctx, p.polylines);
  });
  ctx.globalAlpha = 1;
}

function drawBerth(ctx, lines, c, px) {
  ctx.strokeStyle = c.berth;
  ctx.lineWidth = 3.5 * px;
  strokePolylines(ctx, lines);
}

function labelBerth(ctx, berth, view, c) {
  // at the left end of the visible line, clear of the targets that sit on the quay; a line
  // on the water plane (no quay points near the clicks) says so
  const pts = berth.polylines.flat();
  if (!pts.length) return;
  const left = pts.reduce((a, b) => (b[0] < a[0] ? b : a));
  const [x, y] = toCss(view, Math.max(left[0], 0), left[1]);
  const text = berth.method === "water-plane" ? "BERTH LINE (water plane, ±m)" : "BERTH LINE";
  label(ctx, x + 8, y + 16, text, c.berth, c.targetBg, 12);
}

function drawTarget(ctx, [x, y], t, c, trusted, right, placed) {
  const col = trusted ? c.target : c.untrusted;
  ctx.lineWidth = 4;
  ctx.strokeStyle = "rgba(0,0,0,0.6)";
  ring(ctx, x, y);
  ctx.lineWidth = 2;
  ctx.strokeStyle = col;
  ring(ctx, x, y);
  const name = t.label || t.id;
  const text = `${name}  ${fmtMeasured(t.distance_m, t.distance_sigma_m)}`;
  ctx.font = "700 17px system-ui, sans-serif";
  const w = ctx.measureText(text).width;
  // right of the mark, or left of it near the right edge of the picture; above it, else
  // below it, else further down: the first place no other target's label covers
  const side = x + 14 + w + 6 > right ? [x - 14 - w, x + 14] : [x + 14, x - 14 - w];
  const rows = [y - 16, y + 20, y - 42, y + 46, y - 68, y + 72];
  const box = (lx, ly) => [lx - 4, ly - 12.5, lx + w + 4, ly + 12.5];
  const free = (b) => !placed.some((q) => b[0] < q[2] && q[0] < b[2] && b[1] < q[3] && q[1] < b[3]);
  let at = [side[0], rows[0]];
  search: for (const ly of rows) {
    for (const lx of side) {
      if (free(box(lx, ly))) { at = [lx, ly]; break search; }
    }
  }
  placed.push([...box(at[0], at[1]), text]);
  label(ctx, at[0], at[1], text, col, c.targetBg, 17);
}

function ring(ctx, x, y) {
  ctx.beginPath();
  ctx.arc(x, y, 9, 0, 2 * Math.PI);
  ctx.moveTo(x - 15, y); ctx.lineTo(x - 5, y);
  ctx.moveTo(x + 5, y); ctx.lineTo(x + 15, y);
  ctx.moveTo(x, y - 15); ctx.lineTo(x, y - 5);
  ctx.moveTo(x, y + 5); ctx.lineTo(x, y + 15);
  ctx.stroke();
}

/** A cross where the first berth-line click landed (video and plan). */
export function drawPick(ctx, [x, y], c, half = 9) {
  ctx.strokeStyle = c.berth;
  ctx.lineWidth = 3;
  ctx.beginPath();
  ctx.moveTo(x - half, y - half); ctx.lineTo(x + half, y + half);
  ctx.moveTo(x + half, y - half); ctx.lineTo(x - half, y + half);
  ctx.stroke();
}

/** Text on a dark box: readable on water, sky and quay alike. */
export function label(ctx, x, y, text, color, bg, size = 15) {
  ctx.font = `700 ${size}px system-ui, sans-serif`;
  const w = ctx.measureText(text).width;
  const pad = 4;
  ctx.fillStyle = bg;
  ctx.fillRect(x - pad, y - size / 2 - pad, w + 2 * pad, size + 2 * pad);
  ctx.fillStyle = color;
  ctx.textBaseline = "middle";
  ctx.fillText(text, x, y + 1);
}

/** The legend of the fixed distance bands: a swatch and its range for each. */
export function drawLegend(container, bands, colours) {
  const edges = [0, ...bands];
  container.replaceChildren(...colours.map((col, i) => {
    const item = document.createElement("span");
    item.className = "band";
    const sw = document.createElement("i");
    sw.style.background = col;
    const text = i < bands.length ? `${edges[i]}–${edges[i + 1]}` : `${bands[bands.length - 1]}+`;
    item.append(sw, document.createTextNode(i === bands.length ? `${text} m` : text));
    return item;
  }));
}
