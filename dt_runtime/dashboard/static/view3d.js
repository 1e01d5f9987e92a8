"use strict";
// A small 3D view on a 2D canvas (no WebGL, no library: it draws in any browser, headless
// included, and needs nothing fetched): an orthographic projection of robot-frame points (m)
// after a turn about z (yaw) and a tilt about the screen's horizontal axis (pitch). Dragging
// with the mouse turns the view, the wheel zooms. `draw` is called again on every change.
class View3D {
  constructor(canvas, { scale = 260, center = [0.7, 0, 0.5], yaw = -0.8, pitch = 0.35, interactive = true } = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.scale = scale;       // pixels per metre
    this.center = center;     // the point at the middle of the canvas (m)
    this.yaw = yaw;
    this.pitch = pitch;
    this.onchange = null;
    if (interactive) this._bind();
  }

  _bind() {
    let drag = null;
    this.canvas.addEventListener("pointerdown", (e) => {
      drag = [e.clientX, e.clientY, this.yaw, this.pitch];
      this.canvas.setPointerCapture(e.pointerId);
    });
    this.canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      this.yaw = drag[2] + (e.clientX - drag[0]) * 0.01;
      this.pitch = Math.max(-1.5, Math.min(1.5, drag[3] + (e.clientY - drag[1]) * 0.01));
      this.onchange && this.onchange();
    });
    this.canvas.addEventListener("pointerup", () => { drag = null; });
    this.canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.scale *= Math.exp(-e.deltaY * 0.001);
      this.onchange && this.onchange();
    }, { passive: false });
  }

  // [screen x, screen y, depth] of a point (m); depth grows away from the viewer.
  project(p) {
    const x = p[0] - this.center[0], y = p[1] - this.center[1], z = p[2] - this.center[2];
    const cy = Math.cos(this.yaw), sy = Math.sin(this.yaw);
    const xr = cy * x - sy * y, yr = sy * x + cy * y;
    const cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const up = cp * z - sp * yr, depth = sp * z + cp * yr;
    return [this.canvas.width / 2 + xr * this.scale, this.canvas.height / 2 - up * this.scale, depth];
  }

  clear(bg = "#fbfcfd") {
    this.ctx.fillStyle = bg;
    this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
  }

  line(a, b, color, width = 1, dash = null) {
    const [x0, y0] = this.project(a), [x1, y1] = this.project(b), g = this.ctx;
    g.strokeStyle = color; g.lineWidth = width; g.setLineDash(dash || []);
    g.beginPath(); g.moveTo(x0, y0); g.lineTo(x1, y1); g.stroke();
    g.setLineDash([]);
  }

  polyline(points, color, width = 1, dash = null) {
    if (points.length < 2) return;
    const g = this.ctx;
    g.strokeStyle = color; g.lineWidth = width; g.setLineDash(dash || []); g.lineJoin = "round"; g.lineCap = "round";
    g.beginPath();
    points.forEach((p, i) => { const [x, y] = this.project(p); if (i) g.lineTo(x, y); else g.moveTo(x, y); });
    g.stroke();
    g.setLineDash([]);
  }

  // An arrow from a to b (m) with its head in screen space (a 3D error of 0.1 mm times N).
  arrow(a, b, color, width = 1.5, head = 6) {
    const [x0, y0] = this.project(a), [x1, y1] = this.project(b), g = this.ctx;
    const len = Math.hypot(x1 - x0, y1 - y0);
    g.strokeStyle = color; g.fillStyle = color; g.lineWidth = width; g.setLineDash([]);
    g.beginPath(); g.moveTo(x0, y0); g.lineTo(x1, y1); g.stroke();
    if (len < 1) return;
    const ux = (x1 - x0) / len, uy = (y1 - y0) / len, h = Math.min(head, 0.5 * len);
    g.beginPath(); g.moveTo(x1, y1);
    g.lineTo(x1 - h * ux + 0.5 * h * uy, y1 - h * uy - 0.5 * h * ux);
    g.lineTo(x1 - h * ux - 0.5 * h * uy, y1 - h * uy + 0.5 * h * ux);
    g.closePath(); g.fill();
  }

  dot(p, r, fill, stroke = null) {
    const [x, y] = this.project(p), g = this.ctx;
    g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI);
    g.fillStyle = fill; g.fill();
    if (stroke) { g.strokeStyle = stroke; g.lineWidth = 1; g.stroke(); }
  }

  marker(p, kind, size, color) {
    const [x, y] = this.project(p), g = this.ctx;
    g.strokeStyle = color; g.fillStyle = color; g.lineWidth = 2;
    g.beginPath();
    if (kind === "cross") {
      g.moveTo(x - size, y); g.lineTo(x + size, y); g.moveTo(x, y - size); g.lineTo(x, y + size); g.stroke();
    } else if (kind === "diamond") {
      g.moveTo(x, y - size); g.lineTo(x + size, y); g.lineTo(x, y + size); g.lineTo(x - size, y); g.closePath(); g.fill();
    } else {
      g.arc(x, y, size, 0, 2 * Math.PI); g.stroke();
    }
  }

  // The axis-aligned ellipsoid of semi-axes r (m) about c, as its three principal ellipses.
  ellipsoid(c, r, color) {
    const n = 48;
    for (const [i, j] of [[0, 1], [1, 2], [0, 2]]) {
      const pts = [];
      for (let k = 0; k <= n; k++) {
        const a = (2 * Math.PI * k) / n, p = c.slice();
        p[i] += r[i] * Math.cos(a); p[j] += r[j] * Math.sin(a);
        pts.push(p);
      }
      this.polyline(pts, color, 1.5);
    }
  }

  text(p, s, color = "#333", dx = 6, dy = -6) {
    const [x, y] = this.project(p);
    this.ctx.fillStyle = color; this.ctx.font = "12px system-ui, sans-serif";
    this.ctx.fillText(s, x + dx, y + dy);
  }
}
window.View3D = View3D;
