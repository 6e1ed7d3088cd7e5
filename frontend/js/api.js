// Thin wrappers over the backend's HTTP API. Errors carry the server's own message (the API
// says what is wrong in `detail`), so the page can show it as-is.
//
// Access token: a server off loopback requires one (backend/access.py). The page takes it from
// its URL fragment once (`/#token=…`, printed by the server; a fragment never reaches a server
// log), keeps it in sessionStorage for this tab and removes it from the address bar; it goes
// with every request as `Authorization: Bearer …` and with the stream as `?token=…`.

const TOKEN_KEY = "berthing.token";

function takeToken() {
  const fragment = new URLSearchParams(location.hash.slice(1));
  const given = fragment.get("token");
  if (!given) return;
  sessionStorage.setItem(TOKEN_KEY, given);
  fragment.delete("token");
  const rest = fragment.toString();
  history.replaceState(null, "", location.pathname + location.search + (rest ? `#${rest}` : ""));
}
takeToken();

export function accessToken() {
  return sessionStorage.getItem(TOKEN_KEY);
}

function authHeaders() {
  const token = accessToken();
  return token ? { Authorization: `Bearer ${token}` } : {};
}

const ACCESS_HINT = {
  401: "this server needs an access token: open the address it printed at start (…/#token=…)",
  403: "this page has a read-only token: it may watch, not control",
};

export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

async function request(method, path, body) {
  const init = { method, headers: authHeaders() };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  let res;
  try {
    res = await fetch(path, init);
  } catch (err) {
    throw new ApiError(0, `server unreachable (${err.message})`);
  }
  const text = await res.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = text; }
  if (!res.ok) {
    const detail = data && typeof data === "object" ? data.detail : data;
    const message = typeof detail === "string" ? detail : JSON.stringify(detail ?? res.statusText);
    throw new ApiError(res.status, ACCESS_HINT[res.status] || message);
  }
  return data;
}

export const api = {
  recordings: () => request("GET", "/api/recordings"),
  createSession: (body) => request("POST", "/api/sessions", body),
  session: (id) => request("GET", `/api/sessions/${id}`),
  sessions: () => request("GET", "/api/sessions"),
  deleteSession: (id) =>
    // keepalive: also sent while the page unloads; once unwatched: another tab may have
    // joined the session (and locked targets in it)
    fetch(`/api/sessions/${id}?when_unwatched=true`,
      { method: "DELETE", keepalive: true, headers: authHeaders() }).catch(() => {}),
  control: (id, body) => request("POST", `/api/sessions/${id}/control`, body),
  addTarget: (id, body) => request("POST", `/api/sessions/${id}/targets`, body),
  deleteTarget: (id, targetId) => request("DELETE", `/api/sessions/${id}/targets/${targetId}`),
  setBerthLine: (id, body) => request("PUT", `/api/sessions/${id}/berth-line`, body),
  clearBerthLine: (id) => request("DELETE", `/api/sessions/${id}/berth-line`),
  nudgeBerthLine: (id, body) => request("POST", `/api/sessions/${id}/berth-line/nudge`, body),
  approachLimits: (id) => request("GET", `/api/sessions/${id}/approach-limits`),
  setApproachLimits: (id, body) => request("PUT", `/api/sessions/${id}/approach-limits`, body),
  acknowledgeAlarm: (id, alarmId) =>
    request("POST", `/api/sessions/${id}/alarms/${alarmId}/acknowledge`),
  viewer: () => request("GET", "/api/viewer"),
  followViewer: (session) => request("PUT", "/api/viewer", { session }),
  viewerTheme: (theme) => request("PUT", "/api/viewer/theme", { theme }),
};
