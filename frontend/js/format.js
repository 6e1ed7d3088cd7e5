// How figures are written on the page, in one place.

/** A distance (m) with the digits its range deserves, as crews call them: cm below 5 m, dm
 *  below 50 m, whole metres beyond. */
export function fmtDistance(d) {
  if (d == null || !Number.isFinite(d)) return "–";
  const a = Math.abs(d);
  return d.toFixed(a < 5 ? 2 : a < 50 ? 1 : 0);
}

/** A 1-σ as "±0.25" (cm below 10 m, dm beyond), "" when there is none. */
export function fmtSigma(s) {
  if (s == null || !Number.isFinite(s)) return "";
  return `±${s.toFixed(s < 10 ? 2 : 1)}`;
}

/** A measured distance with its 1-σ, "12.3 ±0.25 m": wherever a target's distance is drawn,
 *  its σ goes with it (a σ of metres is as visible as the figure it qualifies). */
export function fmtMeasured(d, sigma) {
  const pm = fmtSigma(sigma);
  return `${fmtDistance(d)}${pm && ` ${pm}`} m`;
}
