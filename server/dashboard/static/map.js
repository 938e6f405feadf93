// The floor drawn on a canvas in metres: the plan (or the floor's extent), a signal-map overlay, zones with
// their counts, anchors, encounters, people with their 95 % ring and trail, a scale bar and a north
// arrow. Pan by dragging,
// zoom with the wheel; hit-testing gives what was clicked.

export const ANCHOR_STYLE = {
  elevator: ["#6a4c93", "E"], stairs: ["#8d5524", "S"], escalator: ["#8d5524", "Es"], door: ["#386641", "D"],
  turn: ["#1982c4", "T"], magnetic: ["#d62828", "M"], beacon: ["#f77f00", "B"], wifi: ["#0081a7", "W"],
  organic: ["#6c757d", "O"], tag: ["#212529", "Q"],
};
const STALE_MS = 30000;
const ENCOUNTER_FADE_MS = 6000;
const HIT_PX = 10;
const BUSY = 300; // beyond this many people on screen, ellipses are outlines and trails short: overlapping
// shades and long tangles neither read better nor draw cheaply (they are most of a frame's raster time)
const BUSY_TRAIL_POINTS = 5;

// A 2-D Gaussian holds 95 % of its mass within this many sigmas: sqrt of chi-square's 95 % point, 2 dof.
export const RING_95 = Math.sqrt(5.991);

// Eigen-decomposition of a 2x2 covariance: its 95 % ellipse's radii and angle (radians, local frame), and the
// largest sigma.
export function ellipse(cov) {
  const a = cov[0][0], b = cov[0][1], c = cov[1][1];
  const mid = (a + c) / 2, half = Math.sqrt(((a - c) / 2) ** 2 + b * b);
  const l1 = Math.max(mid + half, 0), l2 = Math.max(mid - half, 0);
  return { rx: RING_95 * Math.sqrt(l1), ry: RING_95 * Math.sqrt(l2), angle: 0.5 * Math.atan2(2 * b, a - c), sigma: Math.sqrt(l1) };
}

// A person as the map draws them. The trail is a fixed buffer of `points` positions: a busy floor's page holds
// the same memory after a minute as after an hour.
export function person(est, colour, points) {
  return { id: est.user_id, trail: new Float64Array(2 * points), trailLength: 0, colour, est, ellipse: ellipse(est.covariance_m2) };
}

// The person's newest estimate: its ring, and its position at the trail's end (the oldest dropped when full).
export function moveTo(u, est) {
  u.est = est;
  u.ellipse = ellipse(est.covariance_m2);
  if (2 * u.trailLength === u.trail.length) {
    u.trail.copyWithin(0, 2);
    u.trailLength -= 1;
  }
  u.trail[2 * u.trailLength] = est.position.x_m;
  u.trail[2 * u.trailLength + 1] = est.position.y_m;
  u.trailLength += 1;
}

// Viridis, sampled: enough for a legible heat map without a library.
const VIRIDIS = [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142], [31, 158, 137],
  [53, 183, 121], [110, 206, 88], [181, 222, 43], [253, 231, 37]];
export function viridis(t) {
  const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const i = Math.min(Math.floor(x), VIRIDIS.length - 2), f = x - i;
  return VIRIDIS[i].map((v, k) => Math.round(v + f * (VIRIDIS[i + 1][k] - v)));
}

function niceLength(metres) {
  const p = 10 ** Math.floor(Math.log10(metres));
  for (const m of [1, 2, 5, 10]) if (m * p >= metres) return m * p;
  return 10 * p;
}

export class MapView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.scale = 4; // pixels per metre
    this.ox = 40;
    this.oy = 400;
    this.dirty = true;
    this.scene = null;
    this.bounds = null;
    this.onFrame = null;
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    this.canvas.width = Math.max(1, Math.round(w * dpr));
    this.canvas.height = Math.max(1, Math.round(h * dpr));
    this.dpr = dpr;
    if (this.bounds && !this.userMoved) this.fit(this.bounds);
    this.dirty = true;
  }

  toScreen(x, y) { return [this.ox + x * this.scale, this.oy - y * this.scale]; }
  toWorld(px, py) { return [(px - this.ox) / this.scale, (this.oy - py) / this.scale]; }

  fit(bounds) {
    this.bounds = bounds;
    const [x0, y0, x1, y1] = bounds;
    const w = this.canvas.clientWidth || 800, h = this.canvas.clientHeight || 600;
    const pad = 30;
    this.scale = Math.max(0.05, Math.min((w - 2 * pad) / Math.max(x1 - x0, 1), (h - 2 * pad) / Math.max(y1 - y0, 1)));
    this.ox = (w - (x1 - x0) * this.scale) / 2 - x0 * this.scale;
    this.oy = (h + (y1 - y0) * this.scale) / 2 + y0 * this.scale;
    this.dirty = true;
  }

  zoomAt(px, py, factor) {
    const [wx, wy] = this.toWorld(px, py);
    this.scale = Math.min(Math.max(this.scale * factor, 0.05), 400);
    this.ox = px - wx * this.scale;
    this.oy = py + wy * this.scale;
    this.userMoved = true;
    this.dirty = true;
  }

  pan(dx, dy) {
    this.ox += dx;
    this.oy += dy;
    this.userMoved = true;
    this.dirty = true;
  }

  // What is under a screen point: a person first, then an anchor.
  hit(px, py, scene) {
    let best = null, bestD = HIT_PX;
    for (const u of scene.users.values()) {
      const [sx, sy] = this.toScreen(u.est.position.x_m, u.est.position.y_m);
      const d = Math.hypot(sx - px, sy - py);
      if (d < bestD) { best = { kind: "user", id: u.est.user_id }; bestD = d; }
    }
    if (best) return best;
    for (const a of scene.anchors.values()) {
      if (a.floor !== scene.floor) continue;
      const [sx, sy] = this.toScreen(a.position.x_m, a.position.y_m);
      const d = Math.hypot(sx - px, sy - py);
      if (d < bestD) { best = { kind: "anchor", id: a.id }; bestD = d; }
    }
    return best;
  }

  draw(scene, nowMs) {
    const ctx = this.ctx, dpr = this.dpr;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    ctx.clearRect(0, 0, w, h);
    this.drawFloor(scene);
    if (scene.overlay) this.drawOverlay(scene.overlay);
    this.drawZones(scene);
    this.drawAnchors(scene);
    const fading = this.drawEncounters(scene, nowMs);
    this.drawUsers(scene);
    this.drawScaleBar(h);
    this.drawNorth(scene.geo, w);
    this.dirty = fading;
  }

  drawFloor(scene) {
    const ctx = this.ctx;
    const path = (ring) => {
      ring.forEach(([x, y], i) => {
        const [sx, sy] = this.toScreen(x, y);
        if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      });
      ctx.closePath();
    };
    const polygons = (geometry) => (geometry.type === "Polygon" ? [geometry.coordinates]
      : geometry.type === "MultiPolygon" ? geometry.coordinates : []);
    const lines = (geometry) => (geometry.type === "LineString" ? [geometry.coordinates]
      : geometry.type === "MultiLineString" ? geometry.coordinates : []);
    if (scene.plan) {
      for (const kind of ["walkable", "obstacle", "wall"]) {
        for (const f of scene.plan.features) {
          if (f.properties.kind !== kind) continue;
          ctx.beginPath();
          for (const poly of polygons(f.geometry)) for (const ring of poly) path(ring);
          if (kind === "walkable") { ctx.fillStyle = "#ffffff"; ctx.fill("evenodd"); ctx.strokeStyle = "#7d8a96"; ctx.lineWidth = 2; ctx.stroke(); }
          if (kind === "obstacle") { ctx.fillStyle = "#dfe4ea"; ctx.fill("evenodd"); ctx.strokeStyle = "#9aa6b2"; ctx.lineWidth = 1; ctx.stroke(); }
          if (kind === "wall") { ctx.strokeStyle = "#4a5663"; ctx.lineWidth = 2; ctx.stroke(); }
          if (kind === "wall") {
            ctx.beginPath();
            for (const line of lines(f.geometry)) line.forEach(([x, y], i) => {
              const [sx, sy] = this.toScreen(x, y);
              if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
            });
            ctx.stroke();
          }
        }
      }
    } else if (scene.extent) {
      const [x0, y0, x1, y1] = scene.extent;
      const [sx0, sy0] = this.toScreen(x0, y1), [sx1, sy1] = this.toScreen(x1, y0);
      ctx.fillStyle = "#ffffff";
      ctx.fillRect(sx0, sy0, sx1 - sx0, sy1 - sy0);
      ctx.setLineDash([6, 4]);
      ctx.strokeStyle = "#7d8a96";
      ctx.lineWidth = 1.5;
      ctx.strokeRect(sx0, sy0, sx1 - sx0, sy1 - sy0);
      ctx.setLineDash([]);
    }
  }

  // Each zone of the floor, shaded by whether anyone is in it, named with its count; the outline being drawn.
  drawZones(scene) {
    const ctx = this.ctx;
    const ring = (points) => {
      ctx.beginPath();
      points.forEach(([x, y], i) => {
        const [sx, sy] = this.toScreen(x, y);
        if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      });
    };
    ctx.font = "12px system-ui, sans-serif";
    ctx.textAlign = "center";
    for (const z of scene.zones.values()) {
      if (z.floor !== scene.floor) continue;
      const points = z.polygon.coordinates[0];
      ring(points);
      ctx.closePath();
      ctx.fillStyle = z.occupancy > 0 ? "rgba(255, 159, 28, 0.28)" : "rgba(25, 130, 196, 0.12)";
      ctx.fill();
      ctx.lineWidth = z.id === scene.selectedZone ? 3 : 1.5;
      ctx.strokeStyle = z.occupancy > 0 ? "#e07a00" : "#1982c4";
      ctx.stroke();
      const n = points.length - 1;
      const cx = points.slice(0, n).reduce((a, p) => a + p[0], 0) / n;
      const cy = points.slice(0, n).reduce((a, p) => a + p[1], 0) / n;
      const [sx, sy] = this.toScreen(cx, cy);
      ctx.fillStyle = "#17324d";
      ctx.fillText(`${z.name} · ${z.occupancy}`, sx, sy);
    }
    if (scene.drawing && scene.drawing.length) {
      ring(scene.drawing);
      ctx.setLineDash([5, 4]);
      ctx.strokeStyle = "#e07a00";
      ctx.lineWidth = 2;
      ctx.stroke();
      ctx.setLineDash([]);
      for (const [x, y] of scene.drawing) {
        const [sx, sy] = this.toScreen(x, y);
        ctx.fillStyle = "#e07a00";
        ctx.fillRect(sx - 3, sy - 3, 6, 6);
      }
    }
  }

  // The zone of the floor under a point (the last drawn, when they overlap), or null.
  zoneAt(px, py, scene) {
    const [x, y] = this.toWorld(px, py);
    let found = null;
    for (const z of scene.zones.values()) {
      if (z.floor !== scene.floor) continue;
      const ring = z.polygon.coordinates[0];
      let inside = false;
      for (let i = 0, j = ring.length - 2; i < ring.length - 1; j = i++) {
        const [xi, yi] = ring[i], [xj, yj] = ring[j];
        if ((yi > y) !== (yj > y) && x < xi + ((y - yi) * (xj - xi)) / (yj - yi)) inside = !inside;
      }
      if (inside) found = z.id;
    }
    return found;
  }

  drawOverlay(overlay) {
    const ctx = this.ctx;
    const [sx, sy] = this.toScreen(overlay.x0, overlay.y0 + overlay.rows * overlay.cell);
    ctx.save();
    ctx.globalAlpha = 0.6;
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(overlay.image, sx, sy, overlay.cols * overlay.cell * this.scale, overlay.rows * overlay.cell * this.scale);
    ctx.restore();
  }

  drawAnchors(scene) {
    const ctx = this.ctx;
    for (const a of scene.anchors.values()) {
      if (a.floor !== scene.floor) continue;
      const [sx, sy] = this.toScreen(a.position.x_m, a.position.y_m);
      const [colour, letter] = ANCHOR_STYLE[a.type] || ["#333", "?"];
      const selected = scene.selectedAnchors.has(a.id);
      if (!a.known) {
        const e = ellipse(a.covariance_m2);
        if (e.rx * this.scale > 3) {
          ctx.beginPath();
          ctx.ellipse(sx, sy, e.rx * this.scale, Math.max(e.ry * this.scale, 1), -e.angle, 0, 2 * Math.PI);
          ctx.strokeStyle = colour;
          ctx.globalAlpha = 0.5;
          ctx.setLineDash([3, 3]);
          ctx.lineWidth = 1;
          ctx.stroke();
          ctx.setLineDash([]);
          ctx.globalAlpha = 1;
        }
      }
      const r = 7;
      ctx.beginPath();
      ctx.rect(sx - r, sy - r, 2 * r, 2 * r);
      ctx.fillStyle = a.known ? colour : "#ffffff";
      ctx.fill();
      ctx.lineWidth = selected ? 3 : 1.5;
      ctx.strokeStyle = selected ? "#000000" : colour;
      ctx.stroke();
      ctx.fillStyle = a.known ? "#ffffff" : colour;
      ctx.font = "bold 9px system-ui, sans-serif";
      ctx.textAlign = "center";
      ctx.textBaseline = "middle";
      ctx.fillText(letter, sx, sy + 0.5);
    }
  }

  drawEncounters(scene, nowMs) {
    const ctx = this.ctx;
    let fading = false;
    scene.encounters = scene.encounters.filter((e) => nowMs - e.seenMs < ENCOUNTER_FADE_MS);
    for (const e of scene.encounters) {
      // where the two met, on the floor they met on (a server that sends no places: where they are now)
      if ((e.floor ?? 0) !== scene.floor) continue;
      let pa = e.position_a, pb = e.position_b;
      if (!pa || !pb) {
        const a = scene.users.get(e.user_a), b = scene.users.get(e.user_b);
        if (!a || !b) continue;
        pa = a.est.position;
        pb = b.est.position;
      }
      fading = true;
      const [ax, ay] = this.toScreen(pa.x_m, pa.y_m);
      const [bx, by] = this.toScreen(pb.x_m, pb.y_m);
      ctx.globalAlpha = Math.max(0, 1 - (nowMs - e.seenMs) / ENCOUNTER_FADE_MS);
      ctx.strokeStyle = e.applied ? "#2a9d5b" : "#9aa6b2";
      ctx.setLineDash(e.applied ? [] : [4, 4]);
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.moveTo(ax, ay);
      ctx.lineTo(bx, by);
      ctx.stroke();
    }
    ctx.setLineDash([]);
    ctx.globalAlpha = 1;
    return fading;
  }

  // People drawn by colour: one path a colour for the trails, one for the ellipses, one for the dots, so
  // that a floor of thousands costs a few dozen draw calls a frame, not thousands.
  drawUsers(scene) {
    const ctx = this.ctx;
    const newest = scene.newestMs;
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    const groups = new Map();
    let selected = null;
    for (const u of scene.users.values()) {
      if (u.est.floor !== scene.floor) continue;
      const [sx, sy] = this.toScreen(u.est.position.x_m, u.est.position.y_m);
      const reach = Math.max(u.ellipse.rx * this.scale, 6) + 60;
      if (sx < -reach || sy < -reach || sx > w + reach || sy > h + reach) continue;
      const colour = newest - u.est.t_ms > STALE_MS ? "#9aa6b2" : u.colour;
      if (!groups.has(colour)) groups.set(colour, []);
      groups.get(colour).push([u, sx, sy]);
      if (u.id === scene.selectedUser) selected = [u, sx, sy, colour];
    }
    let onScreen = 0;
    for (const members of groups.values()) onScreen += members.length;
    const shaded = onScreen <= BUSY;
    ctx.lineWidth = 1.5;
    for (const [colour, members] of groups) {
      ctx.beginPath();
      for (const [u] of members) {
        const first = shaded ? 0 : Math.max(0, u.trailLength - BUSY_TRAIL_POINTS);
        for (let i = first; i < u.trailLength; i++) {
          const [tx, ty] = this.toScreen(u.trail[2 * i], u.trail[2 * i + 1]);
          if (i === first) ctx.moveTo(tx, ty); else ctx.lineTo(tx, ty);
        }
      }
      ctx.strokeStyle = colour;
      ctx.globalAlpha = 0.45;
      ctx.stroke();
    }
    ctx.lineWidth = 1;
    for (const [colour, members] of groups) {
      ctx.beginPath();
      for (const [u, sx, sy] of members) {
        const e = u.ellipse;
        const rx = Math.max(e.rx * this.scale, 2), ry = Math.max(e.ry * this.scale, 2);
        ctx.moveTo(sx + rx * Math.cos(-e.angle), sy + rx * Math.sin(-e.angle));
        ctx.ellipse(sx, sy, rx, ry, -e.angle, 0, 2 * Math.PI);
      }
      ctx.fillStyle = colour;
      ctx.strokeStyle = colour;
      if (shaded) {
        ctx.globalAlpha = 0.14;
        ctx.fill();
      }
      ctx.globalAlpha = 0.6;
      ctx.stroke();
    }
    ctx.globalAlpha = 1;
    ctx.lineWidth = 1.2;
    ctx.strokeStyle = "#ffffff";
    for (const [colour, members] of groups) {
      ctx.beginPath();
      for (const [, sx, sy] of members) {
        ctx.moveTo(sx + 4.5, sy);
        ctx.arc(sx, sy, 4.5, 0, 2 * Math.PI);
      }
      ctx.fillStyle = colour;
      ctx.fill();
      ctx.stroke();
    }
    if (selected) {
      const [, sx, sy, colour] = selected;
      ctx.beginPath();
      ctx.arc(sx, sy, 6.5, 0, 2 * Math.PI);
      ctx.fillStyle = colour;
      ctx.fill();
      ctx.lineWidth = 2.5;
      ctx.strokeStyle = "#000000";
      ctx.stroke();
    }
  }

  drawScaleBar(h) {
    const ctx = this.ctx;
    const metres = niceLength(100 / this.scale);
    const px = metres * this.scale;
    const x = 14, y = h - 14;
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.fillRect(x - 6, y - 22, px + 12, 28);
    ctx.strokeStyle = "#1b2530";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x, y - 6); ctx.lineTo(x, y); ctx.lineTo(x + px, y); ctx.lineTo(x + px, y - 6);
    ctx.stroke();
    ctx.fillStyle = "#1b2530";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "alphabetic";
    ctx.fillText(metres >= 1000 ? `${metres / 1000} km` : `${metres} m`, x + px / 2, y - 9);
  }

  // North from the geo-reference: local (x, y) turns counter-clockwise by rotation_rad into (east, north), so
  // north in the local frame is (sin r, cos r).
  drawNorth(geo, w) {
    const ctx = this.ctx;
    const cx = w - 34, cy = 40;
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.beginPath();
    ctx.arc(cx, cy, 24, 0, 2 * Math.PI);
    ctx.fill();
    ctx.font = "bold 11px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    if (!geo) {
      ctx.fillStyle = "#9aa6b2";
      ctx.fillText("N ?", cx, cy);
      return;
    }
    const r = geo.rotation_rad;
    const dx = Math.sin(r), dy = -Math.cos(r); // screen y grows downwards
    ctx.strokeStyle = "#1b2530";
    ctx.fillStyle = "#c0392b";
    ctx.beginPath();
    ctx.moveTo(cx + dx * 16, cy + dy * 16);
    ctx.lineTo(cx - dy * 5 - dx * 6, cy + dx * 5 - dy * 6);
    ctx.lineTo(cx + dy * 5 - dx * 6, cy - dx * 5 - dy * 6);
    ctx.closePath();
    ctx.fill();
    ctx.fillStyle = "#1b2530";
    ctx.fillText("N", cx - dx * 14, cy - dy * 14);
  }
}
