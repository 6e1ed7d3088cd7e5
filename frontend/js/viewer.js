// The free-viewpoint 3-D view (viser, run by the backend on its own port): trajectory in red,
// port structure in blue. Loaded into the tab only when first opened (it streams a scene).

import { api } from "./api.js";
import { currentTheme } from "./theme.js";

export class Viewer {
  constructor(root) {
    this.frame = root.querySelector("#viewer");
    this.link = root.querySelector("#viewer-link");
    this.msg = root.querySelector("#viewer-msg");
    this.url = null;
    this.theme = null; // the colours last set in the 3-D view
  }

  /** Point the viewer at our session and load it. */
  async open(sessionId) {
    try {
      let info = await api.viewer();
      if (info.available && sessionId && info.session !== sessionId) {
        info = await api.followViewer(sessionId);
      }
      if (!info.available || !info.url) throw new Error(info.note || "3-D viewer unavailable");
      this.url = info.url;
      this.link.href = info.url;
      this.msg.hidden = true;
      await this.setTheme(currentTheme());
      if (this.frame.getAttribute("src") !== info.url) this.frame.src = info.url;
    } catch (err) {
      this.msg.hidden = false;
      this.msg.textContent = `3-D view unavailable: ${err.message}`;
    }
  }

  /** The page's day/night colours in the 3-D view too (once it has been opened). */
  async setTheme(name) {
    if (!this.url || this.theme === name) return;
    try {
      await api.viewerTheme(name);
      this.theme = name;
    } catch (err) {
      this.msg.hidden = false;
      this.msg.textContent = `3-D view colours not switched: ${err.message}`;
    }
  }
}
