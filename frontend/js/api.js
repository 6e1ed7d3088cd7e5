// Thin wrappers over the backend's HTTP API. Errors carry the server's own message (the API
// says what is wrong in `detail`), so the page can show it as-is.

export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

async function request(method, path, body) {
  const init = { method, headers: {} };
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
    throw new ApiError(res.status, message);
  }
  return data;
}

export const api = {
  recordings: () => request("GET", "/api/recordings"),
  createSession: (body) => request("POST", "/api/sessions", body),
  session: (id) => request("GET", `/api/sessions/${id}`),
  deleteSession: (id) =>
    // keepalive: also sent while the page unloads
    fetch(`/api/sessions/${id}`, { method: "DELETE", keepalive: true }).catch(() => {}),
  control: (id, body) => request("POST", `/api/sessions/${id}/control`, body),
  addTarget: (id, body) => request("POST", `/api/sessions/${id}/targets`, body),
  deleteTarget: (id, targetId) => request("DELETE", `/api/sessions/${id}/targets/${targetId}`),
  setBerthLine: (id, body) => request("PUT", `/api/sessions/${id}/berth-line`, body),
  clearBerthLine: (id) => request("DELETE", `/api/sessions/${id}/berth-line`),
  acknowledgeAlarm: (id, alarmId) =>
    request("POST", `/api/sessions/${id}/alarms/${alarmId}/acknowledge`),
  viewer: () => request("GET", "/api/viewer"),
  followViewer: (session) => request("PUT", "/api/viewer", { session }),
};
