// Small linear-algebra helpers for the dashboard: poses (rotation quaternion x, y, z, w plus
// translation in metres), column-major 4x4 matrices for WebGL, and pinhole projection.
// Naming follows the project: `target_from_source`, so `world_from_camera * p_camera`.

/** Parses a pose as the API sends it ({rotation_xyzw, translation_m}); also accepts
 *  nalgebra's serde form ({rotation: [x,y,z,w], translation: [x,y,z]}). Returns null if absent. */
export function parsePose(p) {
  if (!p || typeof p !== "object") return null;
  let q = p.rotation_xyzw ?? p.rotation ?? p.quaternion_xyzw;
  let t = p.translation_m ?? p.translation ?? p.position_m;
  if (q && !Array.isArray(q)) q = q.coords ?? q.xyzw ?? [q.x, q.y, q.z, q.w];
  if (t && !Array.isArray(t)) t = t.vector ?? [t.x, t.y, t.z];
  if (!Array.isArray(q) || q.length !== 4 || !Array.isArray(t) || t.length !== 3) return null;
  if (![...q, ...t].every(Number.isFinite)) return null;
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  return { q: q.map((v) => v / n), t: t.slice() };
}

export const IDENTITY_POSE = Object.freeze({ q: [0, 0, 0, 1], t: [0, 0, 0] });

/** Rotates vector v by unit quaternion q = [x, y, z, w]. */
export function rotate(q, v) {
  const [x, y, z, w] = q;
  // t = 2 * cross(q.xyz, v); v' = v + w t + cross(q.xyz, t)
  const tx = 2 * (y * v[2] - z * v[1]);
  const ty = 2 * (z * v[0] - x * v[2]);
  const tz = 2 * (x * v[1] - y * v[0]);
  return [
    v[0] + w * tx + (y * tz - z * ty),
    v[1] + w * ty + (z * tx - x * tz),
    v[2] + w * tz + (x * ty - y * tx),
  ];
}

/** Applies pose a_from_b to a point in b: returns the point in a. */
export function transformPoint(pose, p) {
  const r = rotate(pose.q, p);
  return [r[0] + pose.t[0], r[1] + pose.t[1], r[2] + pose.t[2]];
}

function quatMul(a, b) {
  const [ax, ay, az, aw] = a;
  const [bx, by, bz, bw] = b;
  return [
    aw * bx + ax * bw + ay * bz - az * by,
    aw * by - ax * bz + ay * bw + az * bx,
    aw * bz + ax * by - ay * bx + az * bw,
    aw * bw - ax * bx - ay * by - az * bz,
  ];
}

/** a_from_c = a_from_b * b_from_c. */
export function composePose(aFromB, bFromC) {
  return { q: quatMul(aFromB.q, bFromC.q), t: transformPoint(aFromB, bFromC.t) };
}

/** b_from_a from a_from_b. */
export function invertPose(p) {
  const qi = [-p.q[0], -p.q[1], -p.q[2], p.q[3]];
  const t = rotate(qi, p.t);
  return { q: qi, t: [-t[0], -t[1], -t[2]] };
}

/** Projects a point in the camera's optical frame (x right, y down, z forward) with the 3x3
 *  intrinsic matrix k (row-major nested arrays or flat 9). Returns [u, v] in pixel coordinates
 *  (BOP, OpenCV and ROS: the centre of pixel (x, y) is at (x, y)) or null. */
export function projectPixel(k, pCamera) {
  if (pCamera[2] <= 1e-6) return null;
  const K = flatK(k);
  const x = pCamera[0] / pCamera[2];
  const y = pCamera[1] / pCamera[2];
  return [K[0] * x + K[1] * y + K[2], K[4] * y + K[5]];
}

/** Back-projects pixel coordinates (u, v) to the point at depth z in the camera's optical frame. */
export function unprojectPixel(k, u, v, z) {
  const K = flatK(k);
  const y = (v - K[5]) / K[4];
  const x = (u - K[2] - K[1] * y) / K[0];
  return [x * z, y * z, z];
}

/** Pixel coordinates to image-space coordinates of a canvas showing the whole image at `scale`
 *  canvas pixels per image pixel: pixel (0, 0) covers [0, scale) there, its centre is at
 *  scale / 2. Integer BOP boxes [x, y, w, h] need no shift: their edges are pixel edges. */
export function pixelToCanvas(uv, scale) {
  return [(uv[0] + 0.5) * scale, (uv[1] + 0.5) * scale];
}

/** True when pixel coordinates (u, v) fall on a pixel of a width x height image. */
export function insideImage(uv, width, height) {
  return uv[0] >= -0.5 && uv[1] >= -0.5 && uv[0] < width - 0.5 && uv[1] < height - 0.5;
}

export function flatK(k) {
  if (Array.isArray(k) && Array.isArray(k[0])) return k.flat();
  return k;
}

// ---- 4x4 column-major matrices -----------------------------------------------------------

export function perspective(fovyRad, aspect, near, far) {
  const f = 1 / Math.tan(fovyRad / 2);
  const nf = 1 / (near - far);
  const m = new Float32Array(16);
  m[0] = f / aspect;
  m[5] = f;
  m[10] = (far + near) * nf;
  m[11] = -1;
  m[14] = 2 * far * near * nf;
  return m;
}

function sub(a, b) {
  return [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
}
export function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}
export function normalize(a) {
  const n = Math.hypot(a[0], a[1], a[2]) || 1;
  return [a[0] / n, a[1] / n, a[2] / n];
}
function dot(a, b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

export function lookAt(eye, target, up) {
  const zAxis = normalize(sub(eye, target));
  let xAxis = cross(up, zAxis);
  if (Math.hypot(...xAxis) < 1e-9) xAxis = cross([0, 1, 0], zAxis);
  xAxis = normalize(xAxis);
  const yAxis = cross(zAxis, xAxis);
  const m = new Float32Array(16);
  m[0] = xAxis[0];
  m[4] = xAxis[1];
  m[8] = xAxis[2];
  m[1] = yAxis[0];
  m[5] = yAxis[1];
  m[9] = yAxis[2];
  m[2] = zAxis[0];
  m[6] = zAxis[1];
  m[10] = zAxis[2];
  m[12] = -dot(xAxis, eye);
  m[13] = -dot(yAxis, eye);
  m[14] = -dot(zAxis, eye);
  m[15] = 1;
  return m;
}

export function mul4(a, b) {
  const out = new Float32Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  }
  return out;
}

/** Clip-space transform of a world point by a column-major matrix: returns [x, y, z, w]. */
export function apply4(m, p) {
  return [
    m[0] * p[0] + m[4] * p[1] + m[8] * p[2] + m[12],
    m[1] * p[0] + m[5] * p[1] + m[9] * p[2] + m[13],
    m[2] * p[0] + m[6] * p[1] + m[10] * p[2] + m[14],
    m[3] * p[0] + m[7] * p[1] + m[11] * p[2] + m[15],
  ];
}

/** Sizes a canvas's backing store to its CSS size times the device pixel ratio; returns
 *  `{ w, h, dpr }` (device pixels). */
export function fitCanvas(canvas) {
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(canvas.clientWidth * dpr));
  const h = Math.max(1, Math.round(canvas.clientHeight * dpr));
  if (canvas.width !== w || canvas.height !== h) {
    canvas.width = w;
    canvas.height = h;
  }
  return { w, h, dpr };
}
