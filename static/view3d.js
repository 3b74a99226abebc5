// Hand-written WebGL 1 view of the scene: coloured line segments and round points, with an
// orbit camera (left drag: orbit, right drag or shift+drag: pan, wheel: zoom, double click:
// fit) and 2D text labels drawn on an overlay canvas. World z is up.

import { apply4, fitCanvas, lookAt, mul4, perspective } from "./math.js";

const VERTEX_SHADER = `
attribute vec3 a_position;
attribute vec4 a_color;
attribute float a_size;
uniform mat4 u_clip_from_world;
uniform float u_pixel_ratio;
varying vec4 v_color;
void main() {
  gl_Position = u_clip_from_world * vec4(a_position, 1.0);
  gl_PointSize = a_size * u_pixel_ratio;
  v_color = a_color;
}`;

const FRAGMENT_SHADER = `
precision mediump float;
varying vec4 v_color;
uniform bool u_round;
void main() {
  if (u_round) {
    vec2 d = gl_PointCoord - vec2(0.5);
    if (dot(d, d) > 0.25) discard;
  }
  gl_FragColor = v_color;
}`;

const FLOATS_PER_VERTEX = 8; // x y z, r g b a, size

/** Collects the primitives of one frame. Colours are [r, g, b, a] in 0..1. */
export class SceneGeometry {
  constructor() {
    this.lines = [];
    this.points = [];
    this.labels = [];
    this.pointCount = 0;
    this.lineCount = 0;
  }
  line(a, b, color) {
    this.lines.push(a[0], a[1], a[2], ...color, 1, b[0], b[1], b[2], ...color, 1);
    this.lineCount += 1;
  }
  polyline(pts, color, closed = false) {
    for (let i = 0; i + 1 < pts.length; i++) this.line(pts[i], pts[i + 1], color);
    if (closed && pts.length > 2) this.line(pts[pts.length - 1], pts[0], color);
  }
  point(p, color, sizePx = 4) {
    this.points.push(p[0], p[1], p[2], ...color, sizePx);
    this.pointCount += 1;
  }
  label(p, text, cssColor) {
    this.labels.push({ p, text, cssColor });
  }
  /** Axes triad of a pose (x, y, z coloured by `colors`), length in metres. */
  triad(pose, lengthM, colors, transformPoint) {
    const o = transformPoint(pose, [0, 0, 0]);
    this.line(o, transformPoint(pose, [lengthM, 0, 0]), colors[0]);
    this.line(o, transformPoint(pose, [0, lengthM, 0]), colors[1]);
    this.line(o, transformPoint(pose, [0, 0, lengthM]), colors[2]);
  }
}

export class View3D {
  constructor(canvas, labelCanvas) {
    this.canvas = canvas;
    this.labelCanvas = labelCanvas;
    // `?renderer=canvas2d` forces the fallback (used by the browser test).
    const force2d = new URLSearchParams(location.search).get("renderer") === "canvas2d";
    const gl = force2d ? null : canvas.getContext("webgl", { antialias: true, preserveDrawingBuffer: true });
    this.gl = gl;
    this.geometry = new SceneGeometry();
    // Orbit camera around `target`: yaw about world z, pitch above the xy plane.
    this.orbit = { target: [0, 0, 0], distanceM: 2.5, yawRad: -2.3, pitchRad: 0.55 };
    this.userMoved = false;
    this.dirty = true;
    this.drawnPoints = 0;
    this.drawnLines = 0;
    this.installMouse();
    new ResizeObserver(() => this.requestDraw()).observe(canvas);
    if (!gl) {
      // No WebGL (blocked GPU, old browser): the same picture with Canvas 2D, slower.
      this.ctx2d = canvas.getContext("2d");
      if (!this.ctx2d) throw new Error("neither WebGL nor Canvas 2D is available");
      this.renderer = "canvas2d";
      return;
    }
    this.renderer = "webgl";
    this.program = makeProgram(gl, VERTEX_SHADER, FRAGMENT_SHADER);
    this.loc = {
      position: gl.getAttribLocation(this.program, "a_position"),
      color: gl.getAttribLocation(this.program, "a_color"),
      size: gl.getAttribLocation(this.program, "a_size"),
      clipFromWorld: gl.getUniformLocation(this.program, "u_clip_from_world"),
      pixelRatio: gl.getUniformLocation(this.program, "u_pixel_ratio"),
      round: gl.getUniformLocation(this.program, "u_round"),
    };
    this.lineBuffer = gl.createBuffer();
    this.pointBuffer = gl.createBuffer();
  }

  setGeometry(geometry) {
    this.geometry = geometry;
    this.requestDraw();
  }

  /** Centres the orbit on a bounding sphere unless the user has moved the camera. */
  fit(center, radiusM, force = false) {
    if (this.userMoved && !force) return;
    this.orbit.target = center.slice();
    this.orbit.distanceM = Math.max(0.3, radiusM * 1.9);
    this.requestDraw();
  }

  requestDraw() {
    if (this.dirty && this.pending) return;
    this.dirty = true;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draw();
    });
  }

  clipFromWorld() {
    const o = this.orbit;
    this.canvas.dataset.orbit = `${o.yawRad.toFixed(3)} ${o.pitchRad.toFixed(3)} ${o.distanceM.toFixed(3)}`;
    const cp = Math.cos(o.pitchRad);
    const eye = [
      o.target[0] + o.distanceM * cp * Math.cos(o.yawRad),
      o.target[1] + o.distanceM * cp * Math.sin(o.yawRad),
      o.target[2] + o.distanceM * Math.sin(o.pitchRad),
    ];
    const aspect = this.canvas.width / Math.max(1, this.canvas.height);
    const proj = perspective((45 * Math.PI) / 180, aspect, o.distanceM * 0.01, o.distanceM * 50);
    return mul4(proj, lookAt(eye, o.target, [0, 0, 1]));
  }

  draw() {
    this.dirty = false;
    const gl = this.gl;
    const { w, h, dpr } = fitCanvas(this.canvas);
    if (!gl) {
      this.draw2d(dpr);
      return;
    }
    gl.viewport(0, 0, w, h);
    gl.clearColor(0.09, 0.1, 0.12, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(this.program);
    const m = this.clipFromWorld();
    gl.uniformMatrix4fv(this.loc.clipFromWorld, false, m);
    gl.uniform1f(this.loc.pixelRatio, dpr);
    const g = this.geometry;
    gl.uniform1i(this.loc.round, 0);
    this.drawnLines = this.drawArrays(this.lineBuffer, g.lines, gl.LINES) / 2;
    gl.uniform1i(this.loc.round, 1);
    this.drawnPoints = this.drawArrays(this.pointBuffer, g.points, gl.POINTS);
    this.drawLabels(m, dpr);
    this.canvas.dataset.pointsDrawn = String(this.drawnPoints);
    this.canvas.dataset.linesDrawn = String(this.drawnLines);
  }

  /** Canvas 2D fallback: same primitives, projected on the CPU, no depth test. */
  draw2d(dpr) {
    const ctx = this.ctx2d;
    const W = this.canvas.width;
    const H = this.canvas.height;
    ctx.fillStyle = "rgb(23,26,31)";
    ctx.fillRect(0, 0, W, H);
    const m = this.clipFromWorld();
    const toPx = (x, y, z) => {
      const c = apply4(m, [x, y, z]);
      if (c[3] <= 1e-6) return null;
      return [((c[0] / c[3] + 1) / 2) * W, ((1 - c[1] / c[3]) / 2) * H];
    };
    const css = (d, i) => `rgba(${Math.round(d[i + 3] * 255)},${Math.round(d[i + 4] * 255)},${Math.round(d[i + 5] * 255)},${d[i + 6]})`;
    const L = this.geometry.lines;
    const F = FLOATS_PER_VERTEX;
    ctx.lineWidth = dpr;
    let lines = 0;
    for (let i = 0; i < L.length; i += 2 * F) {
      const a = toPx(L[i], L[i + 1], L[i + 2]);
      const b = toPx(L[i + F], L[i + F + 1], L[i + F + 2]);
      if (!a || !b) continue;
      ctx.strokeStyle = css(L, i);
      ctx.beginPath();
      ctx.moveTo(a[0], a[1]);
      ctx.lineTo(b[0], b[1]);
      ctx.stroke();
      lines += 1;
    }
    const P = this.geometry.points;
    let points = 0;
    for (let i = 0; i < P.length; i += F) {
      const p = toPx(P[i], P[i + 1], P[i + 2]);
      if (!p) continue;
      ctx.fillStyle = css(P, i);
      ctx.beginPath();
      ctx.arc(p[0], p[1], (P[i + 7] * dpr) / 2, 0, 2 * Math.PI);
      ctx.fill();
      points += 1;
    }
    this.drawnLines = lines;
    this.drawnPoints = points;
    this.drawLabels(m, dpr);
    this.canvas.dataset.pointsDrawn = String(points);
    this.canvas.dataset.linesDrawn = String(lines);
  }

  drawArrays(buffer, data, mode) {
    const gl = this.gl;
    const count = data.length / FLOATS_PER_VERTEX;
    if (count === 0) return 0;
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(data), gl.DYNAMIC_DRAW);
    const stride = FLOATS_PER_VERTEX * 4;
    gl.enableVertexAttribArray(this.loc.position);
    gl.vertexAttribPointer(this.loc.position, 3, gl.FLOAT, false, stride, 0);
    gl.enableVertexAttribArray(this.loc.color);
    gl.vertexAttribPointer(this.loc.color, 4, gl.FLOAT, false, stride, 12);
    gl.enableVertexAttribArray(this.loc.size);
    gl.vertexAttribPointer(this.loc.size, 1, gl.FLOAT, false, stride, 28);
    gl.drawArrays(mode, 0, count);
    return count;
  }

  drawLabels(clipFromWorld, dpr) {
    const lc = this.labelCanvas;
    if (lc.width !== this.canvas.width || lc.height !== this.canvas.height) {
      lc.width = this.canvas.width;
      lc.height = this.canvas.height;
    }
    const ctx = lc.getContext("2d");
    ctx.clearRect(0, 0, lc.width, lc.height);
    ctx.font = `${12 * dpr}px system-ui, sans-serif`;
    ctx.textBaseline = "bottom";
    for (const l of this.geometry.labels) {
      const c = apply4(clipFromWorld, l.p);
      if (c[3] <= 0) continue;
      const x = ((c[0] / c[3] + 1) / 2) * lc.width;
      const y = ((1 - c[1] / c[3]) / 2) * lc.height;
      ctx.fillStyle = "rgba(0,0,0,0.6)";
      const wText = ctx.measureText(l.text).width;
      ctx.fillRect(x + 3 * dpr, y - 15 * dpr, wText + 4 * dpr, 15 * dpr);
      ctx.fillStyle = l.cssColor;
      ctx.fillText(l.text, x + 5 * dpr, y - 2 * dpr);
    }
  }

  installMouse() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
      c.setPointerCapture(e.pointerId);
    });
    c.addEventListener("pointerup", (e) => {
      drag = null;
      c.releasePointerCapture(e.pointerId);
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x;
      const dy = e.clientY - drag.y;
      drag.x = e.clientX;
      drag.y = e.clientY;
      const o = this.orbit;
      if (drag.pan) {
        const s = (o.distanceM * 0.8) / Math.max(1, c.clientHeight);
        const right = [-Math.sin(o.yawRad), Math.cos(o.yawRad), 0];
        const upish = [
          -Math.sin(o.pitchRad) * Math.cos(o.yawRad),
          -Math.sin(o.pitchRad) * Math.sin(o.yawRad),
          Math.cos(o.pitchRad),
        ];
        for (let i = 0; i < 3; i++) o.target[i] += (-dx * right[i] + dy * upish[i]) * s;
      } else {
        o.yawRad -= dx * 0.008;
        o.pitchRad = Math.max(-1.5, Math.min(1.5, o.pitchRad + dy * 0.008));
      }
      this.userMoved = true;
      this.requestDraw();
    });
    c.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        this.orbit.distanceM = Math.max(0.05, this.orbit.distanceM * Math.exp(e.deltaY * 0.001));
        this.userMoved = true;
        this.requestDraw();
      },
      { passive: false },
    );
    c.addEventListener("dblclick", () => {
      this.userMoved = false;
      if (this.onFit) this.onFit();
    });
  }
}

function makeProgram(gl, vsSource, fsSource) {
  const compile = (type, src) => {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  };
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl.VERTEX_SHADER, vsSource));
  gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fsSource));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
  return p;
}
