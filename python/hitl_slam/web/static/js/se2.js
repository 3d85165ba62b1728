// SE(2) poses (x, y, theta) for the page: the only copy of the plane geometry in the front end,
// with the conventions of the Rust core (rust/src/se2.rs) and hitl_slam.geometry: headings in
// (-pi, pi], and a pose maps robot-frame points to the world, p_world = R(theta) p + t.
// Poses come as flat arrays (x, y, theta per pose, N*3), scans' points as flat (x, y) pairs.

const TAU = 2 * Math.PI;

/**
 * The angle `a` [rad] wrapped to (-pi, pi], with se2::wrap_angle's arithmetic: an angle already
 * in range is returned unchanged; any other becomes a mod 2 pi in [0, 2 pi), less 2 pi beyond pi
 * (so pi stays pi and -pi becomes pi). NaN and infinities give NaN.
 */
export function wrap(a) {
  if (a > -Math.PI && a <= Math.PI) return a;
  let r = a % TAU; // fmod: the sign of a
  if (r < 0) r += TAU;
  return r > Math.PI ? r - TAU : r;
}

/** The pose `a * b` ([x, y, theta] each): `b` given in the frame of `a`. */
export function compose(a, b) {
  const c = Math.cos(a[2]);
  const s = Math.sin(a[2]);
  return [a[0] + (c * b[0] - s * b[1]), a[1] + (s * b[0] + c * b[1]), wrap(a[2] + b[2])];
}

/** The frame of every pose of `poses` (N*3): a Float64Array of x, y, cos theta, sin theta (N*4). */
export function frames(poses) {
  const n = Math.floor(poses.length / 3);
  const out = new Float64Array(4 * n);
  for (let p = 0; p < n; p++) {
    out[4 * p] = poses[3 * p];
    out[4 * p + 1] = poses[3 * p + 1];
    out[4 * p + 2] = Math.cos(poses[3 * p + 2]);
    out[4 * p + 3] = Math.sin(poses[3 * p + 2]);
  }
  return out;
}

/**
 * Writes the world position of the robot-frame point (px, py) of the pose whose frame is
 * f[o .. o + 4) (x, y, cos, sin; see `frames`) to out[k], out[k + 1].
 */
export function toWorldInto(out, k, f, o, px, py) {
  const c = f[o + 2];
  const s = f[o + 3];
  out[k] = f[o] + c * px - s * py;
  out[k + 1] = f[o + 1] + s * px + c * py;
}

/** The world position [x, y] of the robot-frame point (px, py) seen from pose `pose` [x, y, theta]. */
export function toWorld(pose, px, py) {
  const out = [0, 0];
  toWorldInto(out, 0, [pose[0], pose[1], Math.cos(pose[2]), Math.sin(pose[2])], 0, px, py);
  return out;
}

/**
 * World positions (x, y float32 pairs) of the robot-frame `points` of each scan (pose i's are
 * points[2 offsets[i] .. 2 offsets[i + 1]]) under `poses` (N*3).
 */
export function placePoints(points, offsets, poses) {
  const out = new Float32Array(points.length);
  const f = frames(poses);
  for (let p = 0; p + 1 < offsets.length; p++) {
    for (let i = 2 * offsets[p]; i < 2 * offsets[p + 1]; i += 2) {
      toWorldInto(out, i, f, 4 * p, points[i], points[i + 1]);
    }
  }
  return out;
}

/**
 * World positions (x, y float32 pairs) of the points `indices` (into the flat robot-frame
 * `points`, point i seen by pose owner[i]) under `poses` (N*3); indices beyond `points` are
 * skipped.
 */
export function placeIndexed(points, owner, poses, indices) {
  const out = new Float32Array(2 * indices.length);
  let k = 0;
  for (const i of indices) {
    if (2 * i + 1 >= points.length) continue;
    const q = 3 * owner[i];
    const frame = [poses[q], poses[q + 1], Math.cos(poses[q + 2]), Math.sin(poses[q + 2])];
    toWorldInto(out, k, frame, 0, points[2 * i], points[2 * i + 1]);
    k += 2;
  }
  return out.subarray(0, k);
}
