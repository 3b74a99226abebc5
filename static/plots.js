// Canvas 2D time plots with labelled axes (units included), tick marks and a legend.
// Each plot holds named series of [t_s, y] points; `data-plot-points` on the canvas counts
// the points drawn (a hook for the browser test).

import { fitCanvas } from "./math.js";

const MAX_POINTS_PER_SERIES = 2000;

export class TimePlot {
  /** options: { title, yLabel, yMin, yMax, logY, xLabel } */
  constructor(canvas, options) {
    this.canvas = canvas;
    this.options = { xLabel: "time [s]", ...options };
    this.series = new Map(); // key -> { label, color, dash, points: [[t, y]] }
    this.refLines = []; // { y, label, color }
    this.highlight = null; // key => bool; others are drawn faint and left out of the legend
    this.timeRange = null; // [tMin, tMax] shared by all plots, or null for this plot's own
    this.dirty = true;
  }

  /** Drops the series whose key matches (e.g. of a track the service deleted). */
  removeWhere(predicate) {
    for (const key of [...this.series.keys()]) if (predicate(key)) this.series.delete(key);
    this.dirty = true;
  }

  setHighlight(predicate) {
    this.highlight = predicate;
    this.dirty = true;
  }

  setTimeRange(range) {
    if (range && this.timeRange && range[0] === this.timeRange[0] && range[1] === this.timeRange[1]) return;
    this.timeRange = range;
    this.dirty = true;
  }

  /** [first, last] time of all points, or null. */
  extent() {
    let lo = Infinity;
    let hi = -Infinity;
    for (const s of this.series.values()) {
      if (!s.points.length) continue;
      lo = Math.min(lo, s.points[0][0]);
      hi = Math.max(hi, s.points[s.points.length - 1][0]);
    }
    return Number.isFinite(lo) ? [lo, hi] : null;
  }

  setSeries(key, label, color, dash = []) {
    let s = this.series.get(key);
    if (!s) {
      s = { label, color, dash, points: [] };
      this.series.set(key, s);
    }
    s.label = label;
    s.color = color;
    s.dash = dash;
    return s;
  }

  add(key, tS, y) {
    const s = this.series.get(key);
    if (!s || !Number.isFinite(tS) || !Number.isFinite(y)) return;
    const last = s.points[s.points.length - 1];
    if (last && last[0] === tS) last[1] = y;
    else if (last && tS < last[0]) return; // out of order: ignore
    else s.points.push([tS, y]);
    if (s.points.length > MAX_POINTS_PER_SERIES) s.points.splice(0, s.points.length - MAX_POINTS_PER_SERIES);
    this.dirty = true;
  }

  /** Inserts older points (sorted by time) before the first point of a series. */
  prepend(key, points) {
    const s = this.series.get(key);
    if (!s) return;
    const first = s.points.length ? s.points[0][0] : Infinity;
    const older = points.filter(([t, y]) => t < first && Number.isFinite(y));
    if (!older.length) return;
    s.points = older.concat(s.points).slice(-MAX_POINTS_PER_SERIES);
    this.dirty = true;
  }

  setRefLines(lines) {
    this.refLines = lines;
    this.dirty = true;
  }

  clear() {
    this.series.clear();
    this.dirty = true;
  }

  pointCount() {
    let n = 0;
    for (const s of this.series.values()) n += s.points.length;
    return n;
  }

  draw(force = false) {
    if (!this.dirty && !force) return;
    this.dirty = false;
    const c = this.canvas;
    const { w, h, dpr } = fitCanvas(c);
    const ctx = c.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    const W = w / dpr;
    const H = h / dpr;
    ctx.clearRect(0, 0, W, H);
    const o = this.options;
    const pad = { left: 52, right: 8, top: 18, bottom: 30 };
    const pw = W - pad.left - pad.right;
    const ph = H - pad.top - pad.bottom;

    const isMain = (key) => !this.highlight || this.highlight(key);
    const entries = [...this.series.entries()].filter(([, s]) => s.points.length > 0);
    // Faint series first so that the highlighted ones are drawn on top.
    entries.sort((a, b) => Number(isMain(a[0])) - Number(isMain(b[0])));
    const visible = entries.map(([, s]) => s);
    const mainSeries = entries.filter(([k]) => isMain(k)).map(([, s]) => s);
    const faintCount = entries.length - mainSeries.length;
    let tMin = Infinity;
    let tMax = -Infinity;
    let yMin = Infinity;
    let yMax = -Infinity;
    for (const s of visible) {
      for (const [t, y] of s.points) {
        tMin = Math.min(tMin, t);
        tMax = Math.max(tMax, t);
        if (!o.logY || y > 0) {
          yMin = Math.min(yMin, y);
          yMax = Math.max(yMax, y);
        }
      }
    }
    for (const r of this.refLines) {
      yMin = Math.min(yMin, r.y);
      yMax = Math.max(yMax, r.y);
    }
    if (!Number.isFinite(tMin)) {
      tMin = 0;
      tMax = 10;
    }
    if (this.timeRange) [tMin, tMax] = this.timeRange;
    if (tMax - tMin < 1) tMax = tMin + 1;
    if (o.yMin !== undefined) yMin = o.yMin;
    if (o.yMax !== undefined) yMax = o.yMax;
    if (!Number.isFinite(yMin) || !Number.isFinite(yMax)) {
      yMin = 0;
      yMax = 1;
    }
    if (o.logY && visible.length === 0) {
      yMin = 1e-3;
      yMax = 1e-1;
    } else if (o.logY) {
      yMin = Math.max(yMin, 1e-6);
      yMax = Math.max(yMax, yMin * 10);
    } else if (yMax - yMin < 1e-12) {
      yMax = yMin + Math.max(1e-3, Math.abs(yMin) * 0.1);
    } else if (o.yMin === undefined) {
      yMin = Math.min(0, yMin);
    }
    if (o.yMax === undefined && !o.logY) yMax += (yMax - yMin) * 0.05;

    const ty = o.logY
      ? (y) => pad.top + ph * (1 - (Math.log10(y) - Math.log10(yMin)) / (Math.log10(yMax) - Math.log10(yMin)))
      : (y) => pad.top + ph * (1 - (y - yMin) / (yMax - yMin));
    const tx = (t) => pad.left + (pw * (t - tMin)) / (tMax - tMin);

    // Frame, ticks and labels.
    ctx.strokeStyle = "#667";
    ctx.lineWidth = 1;
    ctx.strokeRect(pad.left, pad.top, pw, ph);
    ctx.fillStyle = "#ccd";
    ctx.font = "11px system-ui, sans-serif";
    ctx.textAlign = "right";
    ctx.textBaseline = "middle";
    const yTicks = o.logY ? logTicks(yMin, yMax) : niceTicks(yMin, yMax, 4);
    for (const v of yTicks) {
      const y = ty(v);
      if (y < pad.top - 0.5 || y > pad.top + ph + 0.5) continue;
      ctx.strokeStyle = "#333844";
      ctx.beginPath();
      ctx.moveTo(pad.left, y);
      ctx.lineTo(pad.left + pw, y);
      ctx.stroke();
      ctx.fillText(formatTick(v), pad.left - 4, y);
    }
    ctx.textAlign = "center";
    ctx.textBaseline = "top";
    for (const v of niceTicks(tMin, tMax, 5)) {
      const x = tx(v);
      if (x < pad.left - 0.5 || x > pad.left + pw + 0.5) continue;
      ctx.strokeStyle = "#667";
      ctx.beginPath();
      ctx.moveTo(x, pad.top + ph);
      ctx.lineTo(x, pad.top + ph + 4);
      ctx.stroke();
      ctx.fillText(formatTick(v), x, pad.top + ph + 5);
    }
    ctx.fillText(o.xLabel, pad.left + pw / 2, pad.top + ph + 17);
    ctx.save();
    ctx.translate(11, pad.top + ph / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.textBaseline = "middle";
    ctx.fillText(o.yLabel, 0, 0);
    ctx.restore();
    ctx.textAlign = "left";
    ctx.textBaseline = "top";
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.fillText(o.title, pad.left, 2);

    // Reference lines (e.g. the decision threshold).
    for (const r of this.refLines) {
      const y = ty(r.y);
      ctx.strokeStyle = r.color;
      ctx.setLineDash([5, 4]);
      ctx.beginPath();
      ctx.moveTo(pad.left, y);
      ctx.lineTo(pad.left + pw, y);
      ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = r.color;
      ctx.font = "10px system-ui, sans-serif";
      ctx.textAlign = "right";
      ctx.textBaseline = "bottom";
      ctx.fillText(r.label, pad.left + pw - 2, y - 1);
    }

    // Series.
    ctx.save();
    ctx.beginPath();
    ctx.rect(pad.left, pad.top, pw, ph);
    ctx.clip();
    let drawn = 0;
    for (const [key, s] of entries) {
      const main = isMain(key);
      ctx.globalAlpha = main ? 1 : 0.35;
      ctx.strokeStyle = s.color;
      ctx.fillStyle = s.color;
      ctx.lineWidth = main ? 2 : 1;
      ctx.setLineDash(s.dash);
      ctx.beginPath();
      let started = false;
      for (const [t, y] of s.points) {
        if (o.logY && y <= 0) continue;
        const x = tx(t);
        const yy = ty(y);
        if (!started) ctx.moveTo(x, yy);
        else ctx.lineTo(x, yy);
        started = true;
        drawn += 1;
      }
      ctx.stroke();
      ctx.setLineDash([]);
      const last = s.points[s.points.length - 1];
      if (last && (!o.logY || last[1] > 0)) {
        ctx.beginPath();
        ctx.arc(tx(last[0]), ty(last[1]), 2.5, 0, 2 * Math.PI);
        ctx.fill();
      }
    }
    ctx.globalAlpha = 1;
    ctx.restore();

    // Legend (top right, inside the frame).
    ctx.font = "11px system-ui, sans-serif";
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    let ly = pad.top + 8;
    const legend = mainSeries.slice();
    if (faintCount > 0) legend.push({ label: "other objects", color: "rgba(200,200,210,0.5)", dash: [] });
    for (const s of legend) {
      const tw = ctx.measureText(s.label).width;
      const lx = pad.left + pw - tw - 30;
      ctx.fillStyle = "rgba(20,22,27,0.75)";
      ctx.fillRect(lx - 3, ly - 7, tw + 32, 14);
      ctx.strokeStyle = s.color;
      ctx.lineWidth = 2;
      ctx.setLineDash(s.dash);
      ctx.beginPath();
      ctx.moveTo(lx, ly);
      ctx.lineTo(lx + 20, ly);
      ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = "#dde";
      ctx.fillText(s.label, lx + 25, ly);
      ly += 14;
    }
    if (visible.length === 0) {
      ctx.fillStyle = "#889";
      ctx.textAlign = "center";
      ctx.fillText("no data yet", pad.left + pw / 2, pad.top + ph / 2);
    }
    c.dataset.plotPoints = String(drawn);
    c.dataset.tMinS = visible.length ? tMin.toFixed(3) : "";
  }
}

export function niceTicks(lo, hi, count) {
  const span = hi - lo;
  if (!(span > 0)) return [lo];
  const raw = span / count;
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => span / s <= count) ?? 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}

function logTicks(lo, hi) {
  const out = [];
  // Fewer than three decades: label 1, 2 and 5 of each decade so the axis is never bare.
  const mantissas = Math.log10(hi / lo) < 3 ? [1, 2, 5] : [1];
  for (let e = Math.floor(Math.log10(lo)); e <= Math.ceil(Math.log10(hi)); e++) {
    for (const m of mantissas) {
      const v = m * Math.pow(10, e);
      if (v >= lo * 0.999 && v <= hi * 1.001) out.push(v);
    }
  }
  return out;
}

export function formatTick(v) {
  if (v === 0) return "0";
  const a = Math.abs(v);
  if (a >= 1000 || a < 0.001) return v.toExponential(0);
  if (a >= 10) return v.toFixed(0);
  if (a >= 1) return v.toFixed(1).replace(/\.0$/, "");
  return String(Number(v.toPrecision(2)));
}
