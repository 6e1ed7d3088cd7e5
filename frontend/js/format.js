// How figures are written on the page, in one place.

/** A distance (m) with the digits its range deserves, as crews call them: cm below 5 m, dm
 *  below 50 m, whole metres beyond. */
export function fmtDistance(d) {
  if (d == null || !Number.isFinite(d)) return "–";
  const a = Math.abs(d);
  return d.toFixed(a < 5 ? 2 : a < 50 ? 1 : 0);
}
