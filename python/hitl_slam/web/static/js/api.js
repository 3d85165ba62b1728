// The HTTP API of `hitl-slam serve` as functions. Every failure (403, 409, 413, 422, 500, network)
// becomes an ApiError whose message says what happened and what to do: callers show it in
// #message, nothing is swallowed here. Binary map arrays arrive as typed arrays over the fetch's
// own ArrayBuffer (no JSON number lists, no copies).

// The page URL's token (?token=...) is kept in memory and sent as a Bearer header, so the API
// also works where the HttpOnly cookie set by GET / is blocked; the token is then removed from
// the address bar (as Jupyter does) so it does not end up in screenshots or history.
let token = null;
{
  const url = new URL(window.location.href);
  token = url.searchParams.get("token");
  if (token !== null) {
    url.searchParams.delete("token");
    window.history.replaceState(null, "", url.pathname + url.search + url.hash);
  }
}

export class ApiError extends Error {
  constructor(message, status = 0, detail = "") {
    super(message);
    this.name = "ApiError";
    this.status = status; // HTTP status, 0 for a network failure
    this.detail = detail; // the server's own words (its "detail"), without what we add
  }
}

function headers(extra = {}) {
  const h = { ...extra };
  if (token) h.Authorization = `Bearer ${token}`;
  return h;
}

async function detailOf(response) {
  try {
    const body = await response.json();
    if (typeof body.detail === "string") return body.detail;
    if (Array.isArray(body.detail)) {
      return body.detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ");
    }
    return JSON.stringify(body);
  } catch {
    return response.statusText || "no details";
  }
}

async function request(path, init = {}) {
  let response;
  try {
    response = await fetch(path, { credentials: "same-origin", cache: "no-store", ...init });
  } catch (err) {
    throw new ApiError(
      `cannot reach the hitl-slam server (${err.message}); is \`hitl-slam serve\` still running?`,
    );
  }
  if (response.ok) return response;
  const detail = await detailOf(response);
  const what = {
    403: "access denied: open the URL printed by `hitl-slam serve` (with its ?token=...)",
    415: "request refused",
    409: "not possible now",
    413: "request too large",
    422: "the server did not understand the request",
  }[response.status] || `server error ${response.status}`;
  throw new ApiError(`${what}: ${detail}`, response.status, detail);
}

async function getJson(path, signal) {
  return (await request(path, { headers: headers(), signal })).json();
}

// Every POST says it is JSON and carries X-Hitl-Slam: the server refuses a POST without them (or
// from another origin), since a page of another site cannot send such a request unpreflighted.
async function postJson(path, body) {
  const init = {
    method: "POST",
    headers: headers({ "Content-Type": "application/json", "X-Hitl-Slam": "1" }),
  };
  if (body !== undefined) init.body = JSON.stringify(body);
  return (await request(path, init)).json();
}

async function getBinary(path) {
  const response = await request(path, { headers: headers() });
  const version = Number(response.headers.get("X-Map-Version"));
  return { buffer: await response.arrayBuffer(), version };
}

/** GET /api/state; with `after`, a long poll that returns once version > after (or in 20 s). */
export function getState(after = null, signal = undefined) {
  return getJson(after === null ? "api/state" : `api/state?after=${after}`, signal);
}

/**
 * The map's scans, fetched once: every point in its robot's frame (P*2 float32) and the per-pose
 * offsets (N+1 int32). They never change; the poses place them.
 */
export async function getScans() {
  const [points, offsets] = await Promise.all([getBinary("api/map/scans"), getBinary("api/map/offsets")]);
  return { points: new Float32Array(points.buffer), offsets: new Int32Array(offsets.buffer) };
}

/** The current poses (N*3 float32) and the state version they are of: all a new map costs. */
export async function getPoses() {
  const poses = await getBinary("api/map/poses");
  return { poses: new Float32Array(poses.buffer), version: poses.version };
}

/** POST /api/interpret: the EM interpretation only (S_a, S_b, P_a, P_b); changes nothing. */
export function interpret(drawn) {
  return postJson("api/interpret", drawn);
}

/** POST /api/corrections: interpret and solve; `accepted: false` is a rejection (map unchanged). */
export function applyCorrection(drawn) {
  return postJson("api/corrections", drawn);
}

/**
 * GET /api/map/info: what the served map is (its poses in words, the front end's verdict and
 * doubtful stretches, a comparison with a bag's own SLAM trajectory), once: it never changes.
 */
export const getMapInfo = () => getJson("api/map/info");

/** GET /api/loop_closures: the map's loop closures (pairs, weight, score, auto_rejected), once. */
export const getLoopClosures = () => getJson("api/loop_closures");

/** POST /api/loop_closures: reject loop closure `index` (or reinstate it); the new State. */
export const setLoopClosure = (index, rejected) => postJson("api/loop_closures", { index, rejected });

/**
 * POST /api/align: match the scans again from the current poses, keeping every correction; the
 * new State (last.kind "align"). A refusal is an ApiError of status 409 (400: no scans), the map
 * unchanged.
 */
export const align = () => postJson("api/align");

export const undo = () => postJson("api/undo");
export const redo = () => postJson("api/redo");
export const journalStep = () => postJson("api/journal/step");
export const save = (name) => postJson("api/save", name ? { name } : {});
export const relations = () => getJson("api/relations");

/** Decodes a base64 string of uint32 little-endian values (S_a / S_b global point indices). */
export function decodeIndices(b64) {
  const bytes = Uint8Array.from(atob(b64 || ""), (c) => c.charCodeAt(0));
  return new Uint32Array(bytes.buffer, 0, bytes.length >>> 2);
}
