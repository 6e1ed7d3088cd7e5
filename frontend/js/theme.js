// Day / night colour schemes. The colours are CSS variables (css/base.css); canvases read them
// here after each switch so that drawing and page always agree.

const KEY = "berthing.theme";

let palette = {};

function read() {
  const css = getComputedStyle(document.documentElement);
  const get = (name) => css.getPropertyValue(name).trim();
  palette = {
    grid: get("--cv-grid"),
    gridOff: get("--cv-grid-off"),
    predict: get("--cv-predict"),
    ship: get("--cv-ship"),
    shipEdge: get("--cv-ship-edge"),
    target: get("--cv-target"),
    targetBg: get("--cv-target-bg"),
    berth: get("--cv-berth"),
    label: get("--cv-label"),
    planBg: get("--cv-plan-bg"),
    planGrid: get("--cv-plan-grid"),
    planText: get("--cv-plan-text"),
    frustum: get("--cv-frustum"),
    hull: get("--cv-hull"),
    untrusted: get("--cv-untrusted"),
    other: get("--cv-point-other"),
    bands: [0, 1, 2, 3, 4, 5, 6].map((i) => get(`--cv-band-${i}`)),
    pointAlpha: parseFloat(get("--cv-point-alpha")) || 1,
    night: document.documentElement.dataset.theme === "night",
  };
}

export function colors() {
  return palette;
}

export function currentTheme() {
  return document.documentElement.dataset.theme;
}

export function setTheme(name) {
  document.documentElement.dataset.theme = name;
  localStorage.setItem(KEY, name);
  read();
}

export function initTheme() {
  const saved = localStorage.getItem(KEY);
  const params = new URLSearchParams(location.search);
  setTheme(params.get("theme") || saved || "day");
}
