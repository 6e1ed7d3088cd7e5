// Designated targets (click-to-measure): the list of points the officer clicked, each with its
// distance from the camera (and its 1-σ) and from the hull, updated every frame from the stream, removable.
// Distances with the digits their range deserves (format.js).
// Rows are updated in place (not rebuilt) so a remove button stays clickable at 10 fps.

import { fmtDistance, fmtSigma } from "./format.js";

export class Targets {
  /** @param {(id: string) => void} onRemove */
  constructor(list, onRemove) {
    this.list = list;
    this.onRemove = onRemove;
    this.rows = new Map();
    this.empty = document.createElement("li");
    this.empty.className = "empty";
    this.empty.textContent = "none — click a point on the quay in the video";
    this.list.append(this.empty);
  }

  update(readouts = []) {
    const seen = new Set();
    for (const t of readouts) {
      seen.add(t.id);
      const row = this.rows.get(t.id) || this._row(t.id);
      row.name.textContent = t.label || t.id;
      // ±1σ of the distance (from the 3-D point's covariance): how far to trust it
      const pm = fmtSigma(t.distance_sigma_m);
      const sigma = pm && `${pm} m · `;
      row.dist.textContent = `${fmtDistance(t.distance_m)} m`;
      // lost: why (the tracker's reason: out of the image, look-alikes, too uncertain a point)
      const state = t.status === "lost" ? ` · lost: ${t.reason || "not found"}`
        : t.visible ? "" : " · out of view";
      row.sub.textContent = `${sigma}hull ${fmtDistance(t.hull_distance_m)} m${state}`;
    }
    for (const [id, row] of this.rows) {
      if (!seen.has(id)) { row.li.remove(); this.rows.delete(id); }
    }
    this.empty.hidden = this.rows.size > 0;
  }

  _row(id) {
    const li = document.createElement("li");
    li.dataset.id = id;
    const name = Object.assign(document.createElement("span"), { className: "tid" });
    const dist = Object.assign(document.createElement("span"), { className: "tdist" });
    const sub = Object.assign(document.createElement("span"), { className: "tsub" });
    const del = Object.assign(document.createElement("button"), {
      className: "btn btn-small", textContent: "✕", title: `Remove ${id}`,
    });
    del.addEventListener("click", () => this.onRemove(id));
    li.append(name, dist, sub, del);
    this.list.append(li);
    const row = { li, name, dist, sub };
    this.rows.set(id, row);
    return row;
  }
}
