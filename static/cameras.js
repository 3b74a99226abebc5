// One panel per camera: the latest depth (or colour) image from the service with the detection
// boxes and every object's particles projected into it (pinhole model, optical frame x right,
// y down, z forward). Images are reloaded at most every MIN_RELOAD_MS per camera.

import { fitCanvas, insideImage, invertPose, parsePose, pixelToCanvas, projectPixel, transformPoint } from "./math.js";

const MIN_RELOAD_MS = 400;
const FRAME_HEIGHT_PX = 190; // matches .camera-frame in style.css

export class CameraPanel {
  constructor(container, camera, colors) {
    this.camera = camera; // scene camera entry
    this.colors = colors; // { cameraCss(id), objectCss(objectId), objectLabel(objectId) }
    this.kind = "depth";
    this.detections = [];
    this.lastLoadMs = 0;
    this.loading = false;
    this.pendingStamp = null;
    this.imageStamp = null;

    const fig = document.createElement("figure");
    fig.className = "camera-panel";
    fig.dataset.camera = camera.id;
    const head = document.createElement("figcaption");
    this.swatch = document.createElement("span");
    this.swatch.className = "swatch";
    this.title = document.createElement("span");
    this.title.className = "camera-title";
    this.toggle = document.createElement("button");
    this.toggle.type = "button";
    this.toggle.className = "small";
    this.toggle.title = "Switch between the depth and the colour image";
    this.toggle.addEventListener("click", () => {
      this.kind = this.kind === "depth" ? "color" : "depth";
      this.lastLoadMs = 0;
      this.reload(this.imageStamp ?? Date.now());
      this.updateCaption();
    });
    head.append(this.swatch, this.title, this.toggle);
    const frame = document.createElement("div");
    frame.className = "camera-frame";
    this.img = document.createElement("img");
    this.img.alt = `latest image of camera ${camera.id}`;
    this.overlay = document.createElement("canvas");
    this.overlay.className = "camera-overlay";
    this.placeholder = document.createElement("div");
    this.placeholder.className = "placeholder";
    this.placeholder.textContent = "waiting for a frame…";
    frame.append(this.img, this.overlay, this.placeholder);
    fig.append(head, frame);
    container.append(fig);
    this.fig = fig;
    this.frame = frame;
    this.img.addEventListener("load", () => {
      this.loading = false;
      this.placeholder.hidden = true;
      this.imageStamp = this.loadedStamp;
      this.fig.dataset.imageLoaded = "true";
      this.drawOverlay();
      if (this.pendingStamp !== null) this.reload(this.pendingStamp);
    });
    this.img.addEventListener("error", () => {
      this.loading = false;
      this.placeholder.hidden = false;
      this.placeholder.textContent = `no ${this.kind === "depth" ? "depth" : "colour"} image yet`;
    });
    this.setCamera(camera);
  }

  setCamera(camera) {
    this.camera = camera;
    this.worldFromCamera = parsePose(camera.world_from_camera);
    this.updateCaption();
    const w = camera.intrinsics?.width ?? 640;
    const h = camera.intrinsics?.height ?? 480;
    // Shrink with the strip (several cameras side by side), never taller than FRAME_HEIGHT_PX.
    this.frame.style.aspectRatio = `${w} / ${h}`;
    this.fig.style.maxWidth = `${Math.round((FRAME_HEIGHT_PX * w) / h)}px`;
  }

  updateCaption() {
    this.swatch.style.background = this.colors.cameraCss(this.camera.id);
    const kindLabel = this.kind === "depth" ? "depth" : "colour";
    this.title.textContent = `${this.camera.id} (${this.camera.mount}) · ${kindLabel}`;
    this.toggle.textContent = this.kind === "depth" ? "colour" : "depth";
  }

  /** Called on every `frame` event of this camera. */
  onFrame(stampNs) {
    this.reload(stampNs);
  }

  reload(stamp) {
    const now = performance.now();
    if (this.loading || now - this.lastLoadMs < MIN_RELOAD_MS) {
      this.pendingStamp = stamp;
      if (!this.loading && !this.timer) {
        this.timer = setTimeout(() => {
          this.timer = null;
          if (this.pendingStamp !== null) this.reload(this.pendingStamp);
        }, MIN_RELOAD_MS);
      }
      return;
    }
    this.pendingStamp = null;
    this.loading = true;
    this.lastLoadMs = now;
    this.loadedStamp = stamp;
    const base = `/api/v1/cameras/${encodeURIComponent(this.camera.id)}/latest`;
    fetch(base)
      .then((r) => (r.ok ? r.json() : null))
      .then((meta) => {
        if (meta) this.detections = Array.isArray(meta.detections) ? meta.detections : [];
      })
      .catch(() => {});
    const file = this.kind === "depth" ? "depth.png" : "color.png";
    this.img.src = `${base}/${file}?stamp=${encodeURIComponent(String(stamp))}`;
  }

  /** Draws the detection boxes and the projected particles of `tracks` over the image. */
  drawOverlay(tracks = this.tracks) {
    this.tracks = tracks ?? [];
    const c = this.overlay;
    const { w, h, dpr } = fitCanvas(c);
    const ctx = c.getContext("2d");
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const intr = this.camera.intrinsics;
    if (!intr) return;
    const s = w / intr.width;
    let projected = 0;
    if (this.worldFromCamera) {
      const cameraFromWorld = invertPose(this.worldFromCamera);
      for (const t of this.tracks) {
        for (const p of t.particles ?? []) {
          const uv = projectPixel(intr.k, transformPoint(cameraFromWorld, p.position_world_m));
          if (!uv || !insideImage(uv, intr.width, intr.height)) continue;
          const [x, y] = pixelToCanvas(uv, s);
          ctx.fillStyle = this.colors.cameraCss(p.camera);
          ctx.fillRect(x - 1.5 * dpr, y - 1.5 * dpr, 3 * dpr, 3 * dpr);
          projected += 1;
        }
      }
    }
    ctx.lineWidth = 2 * dpr;
    ctx.font = `${11 * dpr}px system-ui, sans-serif`;
    ctx.textBaseline = "bottom";
    for (const d of this.detections) {
      const b = d.bbox_xywh_px;
      if (!Array.isArray(b)) continue;
      const color = this.colors.objectCss(d.object);
      ctx.strokeStyle = color;
      ctx.strokeRect(b[0] * s, b[1] * s, b[2] * s, b[3] * s);
      const text = `${this.colors.objectLabel(d.object)} ${Number(d.score ?? 0).toFixed(2)}`;
      const tw = ctx.measureText(text).width;
      ctx.fillStyle = "rgba(0,0,0,0.65)";
      ctx.fillRect(b[0] * s, b[1] * s - 14 * dpr, tw + 4 * dpr, 14 * dpr);
      ctx.fillStyle = color;
      ctx.fillText(text, b[0] * s + 2 * dpr, b[1] * s - 1 * dpr);
    }
    this.fig.dataset.particlesProjected = String(projected);
    this.fig.dataset.detections = String(this.detections.length);
  }
}
