// The dashboard: log in with a key, pick a building, watch it live, replay its last hour, and (operators)
// edit it. Every action goes through the public REST API; its refusals are shown as the server wrote them.

import { Api, ProblemError } from "./api.js";
import { fmtFloor, fmtTime } from "./format.js";
import { LiveSocket } from "./live.js";
import { MapView, ellipse, moveTo, person, viridis, ANCHOR_STYLE } from "./map.js";
import { History } from "./history.js";
import { OperatorTools } from "./tools.js";

const KEY_STORE = "crowdslam.key";
const TRAIL_POINTS = 10; // a short trail: where each person came from, not a tangle
const PALETTE = ["#1d6fb8", "#e76f51", "#2a9d8f", "#8338ec", "#f4a261", "#3a86ff", "#d62828", "#43aa8b", "#ff006e", "#6a994e"];
const $ = (id) => document.getElementById(id);
const root = $("app");

function colourOf(userId) {
  let h = 0;
  for (const ch of userId) h = (h * 31 + ch.charCodeAt(0)) >>> 0;
  return PALETTE[h % PALETTE.length];
}


export function showMessage(text, kind = "error", where = "message") {
  const el = $(where);
  el.textContent = text;
  el.className = `message ${text ? kind : ""}`;
}

export function showProblem(err, where = "message") {
  showMessage(err instanceof ProblemError ? err.describe() : String(err), "error", where);
}

class Dashboard {
  constructor() {
    this.api = null;
    this.identity = null;
    this.live = null;
    this.view = new MapView($("map"));
    this.scene = this.emptyScene();
    this.history = new History(this);
    this.tools = new OperatorTools(this);
    this.picking = false;
    this.bindMap();
    $("login-form").addEventListener("submit", (ev) => {
      ev.preventDefault();
      this.login($("key-input").value.trim());
    });
    for (const id of ["logout", "logout-1"]) $(id).addEventListener("click", () => this.logout(""));
    $("back").addEventListener("click", () => this.showBuildings());
    $("floor").addEventListener("change", () => this.changeFloor(Number($("floor").value)));
    $("overlay").addEventListener("change", () => this.chooseOverlay($("overlay").value));
    $("zoom-in").addEventListener("click", () => this.zoom(1.4));
    $("zoom-out").addEventListener("click", () => this.zoom(1 / 1.4));
    $("zoom-fit").addEventListener("click", () => { this.view.userMoved = false; this.fitFloor(); });
    window.addEventListener("hashchange", () => this.fromFragment());
    requestAnimationFrame((t) => this.frame(t));
  }

  emptyScene() {
    return {
      users: new Map(), anchors: new Map(), encounters: [], floor: 0, plan: null, extent: null, overlay: null,
      geo: null, selectedUser: null, selectedAnchors: new Set(), newestMs: 0, corrections: new Map(),
      zones: new Map(), selectedZone: null, drawing: null,
    };
  }

  // ---------------------------------------------------------------- login
  async start() {
    const fragment = new URLSearchParams(location.hash.slice(1));
    const key = fragment.get("key");
    if (key) {
      // the key leaves the address bar (and the history) at once; the tab keeps it
      fragment.delete("key");
      history.replaceState(null, "", location.pathname + (fragment.toString() ? `#${fragment}` : ""));
      await this.login(key);
      return;
    }
    const stored = sessionStorage.getItem(KEY_STORE);
    if (stored) await this.login(stored);
    else this.showLogin();
  }

  showLogin() {
    for (const id of ["buildings", "live"]) $(id).hidden = true;
    $("login").hidden = false;
    $("key-input").focus();
  }

  async login(key) {
    if (!key) return this.showLogin();
    const api = new Api(key, (err) => this.logout(`Logged out: ${err.message}`));
    showMessage("", "", "login-message");
    try {
      this.identity = await api.get("/v1/key");
    } catch (err) {
      sessionStorage.removeItem(KEY_STORE);
      this.showLogin();
      showProblem(err, "login-message");
      return;
    }
    if (this.identity.scope === "device") {
      this.showLogin();
      showMessage("This is a device key: phones post with it. Log in with a dashboard or operator key.", "error", "login-message");
      return;
    }
    this.api = api;
    sessionStorage.setItem(KEY_STORE, key);
    $("key-input").value = "";
    $("scope").textContent = `${this.identity.scope} key`;
    await this.fromFragment(true);
  }

  logout(reason) {
    if (this.live) this.live.stop();
    this.live = null;
    this.watchHealth(null);
    this.api = null; // first: nothing below may ask the server with the key any more
    this.history.stop();
    this.identity = null;
    sessionStorage.removeItem(KEY_STORE);
    this.scene = this.emptyScene();
    root.dataset.building = "";
    root.dataset.users = "0";
    root.dataset.updatedMs = "0";
    root.dataset.connection = "idle";
    history.replaceState(null, "", location.pathname);
    this.showLogin();
    showMessage(reason || "", reason ? "error" : "", "login-message");
  }

  async fromFragment(afterLogin = false) {
    if (!this.api) return;
    const building = new URLSearchParams(location.hash.slice(1)).get("building");
    if (building && building !== root.dataset.building) await this.openBuilding(building);
    else if (!building && (afterLogin || root.dataset.building)) await this.showBuildings(afterLogin);
  }

  async showBuildings(autoOpen = false) {
    this.watchHealth(null);
    if (this.live) this.live.stop();
    this.live = null;
    root.dataset.building = "";
    $("login").hidden = true;
    $("live").hidden = true;
    $("buildings").hidden = false;
    let buildings = [];
    try {
      buildings = await this.api.get("/v1/buildings");
    } catch (err) {
      showProblem(err, "buildings-message");
      return;
    }
    if (autoOpen && buildings.length === 1) {
      location.hash = `building=${encodeURIComponent(buildings[0].id)}`;
      return;
    }
    history.replaceState(null, "", location.pathname);
    const list = $("building-list");
    list.replaceChildren(...buildings.map((b) => {
      const li = document.createElement("li");
      const button = document.createElement("button");
      button.type = "button";
      button.className = "quiet";
      button.dataset.id = b.id;
      button.textContent = `${b.name} (${b.id}), ${b.floors.length || 1} floor${b.floors.length === 1 ? "" : "s"}`;
      button.addEventListener("click", () => { location.hash = `building=${encodeURIComponent(b.id)}`; });
      li.append(button);
      return li;
    }));
    showMessage(buildings.length ? "" : "This key sees no building yet.", "ok", "buildings-message");
  }

  // ---------------------------------------------------------------- a building, live
  async openBuilding(id) {
    if (this.live) this.live.stop();
    this.history.stop();
    const previousFloor = this.scene.floor;
    this.scene = this.emptyScene();
    this.dropped = 0;
    $("drops").hidden = true;
    this.view.userMoved = false;
    let building;
    try {
      building = await this.api.get(`/v1/buildings/${encodeURIComponent(id)}`);
    } catch (err) {
      await this.showBuildings();
      showProblem(err, "buildings-message");
      return;
    }
    this.building = building;
    $("login").hidden = true;
    $("buildings").hidden = true;
    $("live").hidden = false;
    $("building-name").textContent = building.name;
    this.scene.geo = building.geo_reference;
    const levels = building.floors.length ? building.floors.map((f) => f.level) : [0];
    $("floor").replaceChildren(...levels.map((level) => {
      const f = building.floors.find((x) => x.level === level);
      const option = new Option(f ? `${f.name} (${level})` : `${level}`, String(level));
      option.dataset.name = option.textContent;
      return option;
    }));
    this.scene.floor = levels.includes(previousFloor) ? previousFloor : levels.includes(0) ? 0 : levels[0];
    $("floor").value = String(this.scene.floor);
    root.dataset.building = building.id;
    showMessage("");
    this.tools.show(this.identity.scope === "operator");
    await Promise.all([
      this.loadFloor(), this.loadAnchors(), this.loadZones(), this.loadPositions(), this.loadOverlays(),
    ]);
    this.fitFloor();
    this.live = new LiveSocket({
      buildingId: building.id,
      key: this.api.key,
      onMessages: (messages) => this.onLive(messages),
      onState: (state, note, reconnected) => this.onConnection(state, note, reconnected),
      onRefused: (reason) => this.logout(`Logged out: the server refused the key (${reason}).`),
    });
    this.live.start();
    this.watchHealth(building.id);
  }

  // The server's own trouble with this building (/healthz's failing_buildings), checked every 15 s while
  // the building is open: a building that cannot be loaded, or failed batches lately.
  watchHealth(buildingId) {
    clearInterval(this.healthTimer);
    this.healthTimer = null;
    $("health").hidden = true;
    if (buildingId === null) return;
    const check = async () => {
      if (!this.api || !this.building || this.building.id !== buildingId) return;
      let health;
      try {
        health = await this.api.get("/healthz");
      } catch (err) {
        return; // the live badge already says when the server cannot be reached
      }
      const trouble = (health.failing_buildings || []).find((f) => f.building_id === buildingId);
      const badge = $("health");
      badge.hidden = !trouble;
      root.dataset.failing = trouble ? "true" : "false";
      if (!trouble) return;
      const parts = [];
      if (trouble.failed_loads) parts.push(`cannot be loaded (${trouble.failed_loads} attempts)`);
      if (trouble.failed_batches) parts.push(`${trouble.failed_batches} batches failed`);
      if (trouble.unreplayed_batches) parts.push(`${trouble.unreplayed_batches} batches lost in a restart`);
      badge.textContent = `server error: ${parts.join(", ")}`;
      badge.title = `The server's own error, logged for its operators; latest ${fmtTime(trouble.last_failure_ms)}`;
    };
    check();
    this.healthTimer = setInterval(check, 15000);
  }

  message(text, kind = "error") { showMessage(text, kind); }
  problem(err) { showProblem(err); }
  refresh() {
    this.tools.selectionChanged();
    this.renderLegend();
    this.renderDetails();
    this.view.dirty = true;
  }

  path(suffix) { return `/v1/buildings/${encodeURIComponent(this.building.id)}${suffix}`; }

  async loadFloor() {
    const floor = this.building.floors.find((f) => f.level === this.scene.floor);
    this.scene.extent = floor && floor.width_m && floor.height_m ? [0, 0, floor.width_m, floor.height_m] : null;
    this.scene.plan = null;
    try {
      const levels = await this.api.get(this.path("/floor-plans"));
      if (levels.includes(this.scene.floor)) this.scene.plan = await this.api.get(this.path(`/floors/${this.scene.floor}/plan`));
    } catch (err) {
      showProblem(err);
    }
    this.renderLegend();
    this.view.dirty = true;
  }

  async loadAnchors() {
    try {
      const anchors = await this.api.get(this.path("/anchors"));
      this.scene.anchors = new Map(anchors.map((a) => [a.id, a]));
    } catch (err) {
      showProblem(err);
    }
    this.renderLegend();
    this.view.dirty = true;
  }

  async loadZones() {
    try {
      const zones = await this.api.get(this.path("/zones"));
      this.scene.zones = new Map(zones.map((z) => [z.id, z]));
    } catch (err) {
      showProblem(err);
    }
    this.publishZones();
    this.view.dirty = true;
  }

  // Each zone's count where tests and people read it: data-zones="id:count,...".
  publishZones() {
    root.dataset.zones = [...this.scene.zones.values()].map((z) => `${z.id}:${z.occupancy}`).join(",");
  }

  async loadPositions() {
    try {
      const estimates = await this.api.get(this.path("/positions"));
      if (!this.history.active) for (const e of estimates) this.updateUser(e);
      this.published();
    } catch (err) {
      showProblem(err);
    }
  }

  async changeFloor(level) {
    this.scene.floor = level;
    this.scene.overlay = null; // another floor's signals: choose again among this floor's
    this.view.userMoved = false;
    await Promise.all([this.loadFloor(), this.loadOverlays()]);
    this.fitFloor();
    this.published();
  }

  fitFloor() {
    const s = this.scene;
    let bounds = null;
    const grow = (x, y) => {
      bounds = bounds ? [Math.min(bounds[0], x), Math.min(bounds[1], y), Math.max(bounds[2], x), Math.max(bounds[3], y)] : [x, y, x, y];
    };
    if (s.plan) {
      const walk = (c) => (typeof c[0] === "number" ? grow(c[0], c[1]) : c.forEach(walk));
      for (const f of s.plan.features) walk(f.geometry.coordinates);
    } else if (s.extent) {
      grow(s.extent[0], s.extent[1]);
      grow(s.extent[2], s.extent[3]);
    }
    if (!bounds) {
      for (const u of s.users.values()) grow(u.est.position.x_m, u.est.position.y_m);
      for (const a of s.anchors.values()) grow(a.position.x_m, a.position.y_m);
    }
    this.view.fit(bounds || [0, 0, 50, 50]);
  }

  zoom(factor) {
    const c = $("map");
    this.view.zoomAt(c.clientWidth / 2, c.clientHeight / 2, factor);
  }

  updateUser(est, trail = true) {
    let u = this.scene.users.get(est.user_id);
    if (!u) {
      u = person(est, colourOf(est.user_id), TRAIL_POINTS);
      this.scene.users.set(est.user_id, u);
    }
    if (est.t_ms < u.est.t_ms && u.trailLength) return; // an older estimate after a newer one
    if (!trail) u.trailLength = 0;
    moveTo(u, est);
    if (est.source === "fix" || est.source === "fingerprint") this.correction(est.user_id, `${est.source} at ${fmtTime(est.t_ms)}`);
    if (est.t_ms > this.scene.newestMs) this.scene.newestMs = est.t_ms;
  }

  correction(userId, text) {
    const list = this.scene.corrections.get(userId) || [];
    list.push(text);
    if (list.length > 5) list.shift();
    this.scene.corrections.set(userId, list);
  }

  onLive(messages) {
    let anchorsChanged = false;
    for (const m of messages) {
      if (m.type === "position") {
        if (!this.history.active) this.updateUser(m.estimate);
      } else if (m.type === "encounter") {
        const e = m.encounter;
        if (!this.history.active) this.scene.encounters.push({ ...e, seenMs: performance.now() });
        const said = (other) => (e.applied
          ? `met ${other} about ${e.distance_m.toFixed(0)} m away (${e.model}): position refined, ${fmtTime(e.t_ms)}`
          : `an encounter with ${other} (${e.model}) did not fit and was ignored, ${fmtTime(e.t_ms)}`);
        this.correction(e.user_a, said(e.user_b));
        this.correction(e.user_b, said(e.user_a));
      } else if (m.type === "anchor") {
        if (m.deleted) this.scene.anchors.delete(m.anchor.id);
        else this.scene.anchors.set(m.anchor.id, m.anchor);
        anchorsChanged = true;
      } else if (m.type === "zone") {
        const z = this.scene.zones.get(m.zone_id);
        if (z && m.kind !== "dwell") z.occupancy = Math.max(0, z.occupancy + (m.kind === "enter" ? 1 : -1));
        const name = z ? z.name : m.zone_id;
        const said = { enter: "entered", exit: "left", dwell: "has stayed in" }[m.kind];
        this.correction(m.user_id, `${said} ${name} (p ${m.probability.toFixed(2)}), ${fmtTime(m.t_ms)}`);
        this.publishZones();
        const inside = $("zone-inside"); // the selected zone's count; its visits are fetched when it is chosen
        if (z && inside && this.scene.selectedZone === m.zone_id) inside.textContent = String(z.occupancy);
      } else if (m.type === "user_forgotten") {
        this.scene.users.delete(m.user_id);
        this.scene.corrections.delete(m.user_id);
        if (this.scene.selectedUser === m.user_id) this.scene.selectedUser = null;
      } else if (m.type === "heartbeat" && m.dropped > 0) {
        this.dropped = (this.dropped || 0) + m.dropped;
        $("drops").hidden = false;
        $("drops").textContent = `${this.dropped} updates dropped (slow connection)`;
      }
    }
    if (anchorsChanged) this.renderLegend(); // a type learned for the first time gets its legend line
    this.published();
  }

  // The page's state as tests and people read it.
  published() {
    const s = this.scene;
    let drawn = 0, newest = 0;
    const perFloor = new Map();
    for (const u of s.users.values()) {
      perFloor.set(u.est.floor, (perFloor.get(u.est.floor) || 0) + 1);
      if (u.est.floor !== s.floor) continue;
      drawn += 1;
      newest = Math.max(newest, u.est.t_ms);
    }
    root.dataset.users = String(drawn);
    root.dataset.updatedMs = String(newest);
    for (const option of $("floor").options) { // where everyone is, floor by floor, without switching
      const label = `${option.dataset.name} · ${perFloor.get(Number(option.value)) || 0} people`;
      if (option.textContent !== label) option.textContent = label;
    }
    $("status-line").textContent = this.history.active
      ? `replaying: ${drawn} people on this floor at ${$("history-time").textContent}`
      : `${drawn} people on this floor · newest update ${fmtTime(newest)}`;
    this.view.dirty = true;
    if (this.scene.selectedUser) this.renderDetails(); // the selected person's figures, as they change
  }

  onConnection(state, note, reconnected) {
    root.dataset.connection = state;
    const badge = $("connection");
    badge.dataset.state = state;
    badge.textContent = state === "connected" ? "live" : note ? `${state}: ${note}` : state;
    if (state === "connected" && reconnected) {
      // what happened while the socket was down: positions and anchors as they are now
      this.loadPositions();
      this.loadAnchors();
    }
  }

  // ---------------------------------------------------------------- overlay
  async loadOverlays() {
    const select = $("overlay");
    select.replaceChildren(new Option("none", ""));
    $("overlay-note").textContent = "";
    let jobs = [];
    try {
      jobs = await this.api.get(this.path("/signal-maps"));
    } catch (err) {
      showProblem(err);
      return;
    }
    const done = jobs.filter((j) => j.status === "done").sort((a, b) => (a.finished_at < b.finished_at ? 1 : -1));
    if (!done.length) {
      $("overlay-note").textContent = "No finished signal-map build yet.";
      return;
    }
    const job = done[0];
    this.overlayJob = job;
    // a build of several floors names each floor's maps "floor<level>_signal_map_..."; of one, "signal_map_..."
    const several = job.files.some((f) => /^floor-?\d+_/.test(f));
    const mapped = job.floors && job.floors.length ? job.floors : [0]; // builds before floors mapped floor 0
    const prefix = several ? `floor${this.scene.floor}_signal_map_` : mapped.includes(this.scene.floor) ? "signal_map_" : null;
    const names = prefix === null ? [] : job.files.filter((f) => f.startsWith(prefix) && f.endsWith(".json"));
    for (const name of names) {
      const kind = name.includes("_ap") ? "WiFi AP" : name.includes("_cell") ? "LTE cell" : "magnetic";
      select.append(new Option(`${kind} ${name.slice(prefix.length).replace(/\.json$/, "")}`, name));
    }
    $("overlay-note").textContent = names.length
      ? `Build ${job.id}, finished ${fmtTime(Date.parse(job.finished_at))}.`
      : `Build ${job.id} mapped no signal on this floor.`;
  }

  async chooseOverlay(name) {
    this.scene.overlay = null;
    this.view.dirty = true;
    if (!name) return this.renderLegend();
    try {
      const grid = await this.api.get(this.path(`/signal-maps/${this.overlayJob.id}/files/${encodeURIComponent(name)}`));
      this.scene.overlay = this.overlayImage(grid);
      this.view.dirty = true;
      $("overlay-note").textContent = `${this.scene.overlay.label}, mean of the readings placed by SignalSLAM`;
    } catch (err) {
      showProblem(err);
    }
    this.renderLegend();
  }

  overlayImage(grid) {
    const key = Object.keys(grid).find((k) => k.startsWith("mean_"));
    const mean = grid[key];
    const rows = mean.length, cols = rows ? mean[0].length : 0;
    let lo = Infinity, hi = -Infinity;
    for (const row of mean) for (const v of row) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    const canvas = document.createElement("canvas");
    canvas.width = Math.max(cols, 1);
    canvas.height = Math.max(rows, 1);
    const ctx = canvas.getContext("2d");
    const image = ctx.createImageData(canvas.width, canvas.height);
    for (let r = 0; r < rows; r++) for (let c = 0; c < cols; c++) {
      const v = mean[r][c];
      if (v === null) continue;
      const [red, green, blue] = viridis((v - lo) / Math.max(hi - lo, 1e-9));
      const i = ((rows - 1 - r) * cols + c) * 4; // row 0 is the southmost: the image's last line
      image.data.set([red, green, blue, 255], i);
    }
    ctx.putImageData(image, 0, 0);
    const unit = { mean_dbm: "dBm", mean_ut: "µT" }[key] || key.replace(/^mean_/, "");
    const name = grid.bssid ? `AP ${grid.bssid}` : grid.cell_id ? `cell ${grid.cell_id}` : grid.field;
    return {
      image: canvas, x0: grid.origin_m[0] - grid.cell_m / 2, y0: grid.origin_m[1] - grid.cell_m / 2, cell: grid.cell_m,
      rows, cols, lo, hi, label: `${name}: ${lo.toFixed(0)} to ${hi.toFixed(0)} ${unit}`,
    };
  }

  // ---------------------------------------------------------------- legend and details
  renderLegend() {
    const rows = [];
    const row = (swatch, text) => {
      const d = document.createElement("div");
      if (swatch) d.append(swatch);
      d.append(text);
      rows.push(d);
    };
    const swatch = (background, { square = false, letter = "", cls = "swatch" } = {}) => {
      const span = document.createElement("span");
      span.className = cls;
      span.style.background = background; // set through the CSSOM: the page's CSP allows no style attribute
      if (square) span.style.borderRadius = "2px";
      if (letter) Object.assign(span.style, { color: "#fff", fontSize: "9px", textAlign: "center", lineHeight: "14px" });
      span.textContent = letter;
      return span;
    };
    row(swatch("#1d6fb8"), "a person (a colour each); the ring holds them with 95 % probability");
    row(swatch("#9aa6b2"), "no update for 30 s");
    const types = new Set([...this.scene.anchors.values()].filter((a) => a.floor === this.scene.floor).map((a) => a.type));
    for (const t of types) {
      const [colour, letter] = ANCHOR_STYLE[t] || ["#333", "?"];
      row(swatch(colour, { square: true, letter }), `${t} anchor`);
    }
    if (types.size) row(null, "filled: pinned by an operator; hollow with a dashed ring: learned by the crowd");
    const line = swatch("transparent");
    Object.assign(line.style, { width: "18px", height: "0", borderRadius: "0", borderTop: "2px solid #2a9d5b" });
    row(line, "two people met (an encounter)");
    if (this.scene.overlay) {
      const stops = Array.from({ length: 10 }, (_, i) => `rgb(${viridis(i / 9).join(",")})`).join(",");
      row(swatch(`linear-gradient(to right, ${stops})`, { cls: "ramp" }), this.scene.overlay.label);
    }
    if (!this.scene.plan) row(null, this.scene.extent ? "dashed: the floor's extent (no plan uploaded)" : "no floor plan or extent");
    if (!this.scene.geo) row(null, "north unknown: the building has no geo-reference");
    $("legend").replaceChildren(...rows);
  }

  renderDetails() {
    const body = $("details-body");
    const s = this.scene;
    const dl = (pairs) => {
      const list = document.createElement("dl");
      for (const [k, v] of pairs) {
        const dt = document.createElement("dt"); dt.textContent = k;
        const dd = document.createElement("dd"); dd.textContent = v;
        list.append(dt, dd);
      }
      return list;
    };
    if (s.selectedUser && s.users.has(s.selectedUser)) {
      const u = s.users.get(s.selectedUser);
      const items = (s.corrections.get(u.id) || []).slice().reverse();
      const list = document.createElement("ul");
      list.replaceChildren(...(items.length ? items : ["none seen since the page opened"]).map((t) => { const li = document.createElement("li"); li.textContent = t; return li; }));
      const heading = document.createElement("p");
      heading.className = "hint";
      heading.textContent = "Recent corrections";
      body.replaceChildren(dl([
        ["person", u.id], ["device", u.est.device_id],
        ["position", `${u.est.position.x_m.toFixed(1)}, ${u.est.position.y_m.toFixed(1)} m`],
        ["sigma", `${u.ellipse.sigma.toFixed(1)} m (95 % within ${(2 * u.ellipse.sigma).toFixed(1)} m)`],
        ["estimated by", u.est.source], ["floor", fmtFloor(u.est)], ["last update", fmtTime(u.est.t_ms)],
      ]), heading, list);
      return;
    }
    if (s.selectedZone && s.zones.has(s.selectedZone)) {
      this.renderZone(s.zones.get(s.selectedZone), dl, body);
      return;
    }
    const ids = [...s.selectedAnchors];
    if (ids.length === 1 && s.anchors.has(ids[0])) {
      const a = s.anchors.get(ids[0]);
      const e = ellipse(a.covariance_m2);
      body.replaceChildren(dl([
        ["anchor", a.id], ["type", a.type], ["label", a.label || "none"],
        ["kind", a.known ? "pinned by an operator" : "learned by the crowd"],
        ["position", `${a.position.x_m.toFixed(1)}, ${a.position.y_m.toFixed(1)} m`],
        ["uncertainty", `${e.sigma.toFixed(2)} m (1 sigma)`], ["observations", String(a.observation_count)],
        ["last seen", fmtTime(a.last_seen_ms)], ...(a.signature ? [["signature", a.signature]] : []),
      ]));
      return;
    }
    if (ids.length > 1) {
      body.replaceChildren(dl([["selected anchors", ids.join(", ")]]));
      return;
    }
    const p = document.createElement("p");
    p.className = "hint";
    p.textContent = "Click a person or an anchor on the map.";
    body.replaceChildren(p);
  }

  // A zone's figures, then its visits of the last day and a histogram of how long they lasted.
  renderZone(z, dl, body) {
    body.replaceChildren(dl([
      ["zone", z.id], ["name", z.name], ["floor", String(z.floor)], ["inside now", String(z.occupancy)],
      ["dwell event", z.dwell_s ? `after ${z.dwell_s} s` : "none"],
    ]));
    body.querySelectorAll("dd")[3].id = "zone-inside";
    const since = Date.now() - 86400000;
    const asked = z.id;
    this.api.get(this.path(`/zones/${encodeURIComponent(z.id)}/visits?since=${since}&limit=1000`)).then((visits) => {
      if (this.scene.selectedZone !== asked) return;
      const closed = visits.filter((v) => v.seconds !== null);
      const bins = [["< 1 min", 60], ["1-5 min", 300], ["5-15 min", 900], ["15-60 min", 3600], ["> 1 h", Infinity]];
      const counts = bins.map(() => 0);
      for (const v of closed) counts[bins.findIndex(([, top]) => v.seconds < top)] += 1;
      const most = Math.max(1, ...counts);
      const heading = document.createElement("p");
      heading.className = "hint";
      heading.textContent = `${visits.length} visits in the last 24 h (${visits.length - closed.length} inside now)`;
      const chart = document.createElement("div");
      chart.className = "histogram";
      chart.replaceChildren(...bins.map(([label], k) => {
        const row = document.createElement("div");
        const bar = document.createElement("span");
        bar.className = "bar";
        bar.style.width = `${(100 * counts[k]) / most}%`;
        row.append(Object.assign(document.createElement("span"), { textContent: label, className: "label" }), bar,
          Object.assign(document.createElement("span"), { textContent: String(counts[k]) }));
        return row;
      }));
      const list = document.createElement("ul");
      list.replaceChildren(...visits.slice(-8).reverse().map((v) => {
        const li = document.createElement("li");
        li.textContent = `${v.user_id}: ${fmtTime(v.entered_ms)}${v.seconds === null ? ", inside" : `, ${Math.round(v.seconds)} s`}`;
        return li;
      }));
      body.append(heading, chart, list);
    }).catch((err) => showProblem(err));
  }

  // ---------------------------------------------------------------- the map's input
  bindMap() {
    const canvas = $("map");
    let drag = null;
    canvas.addEventListener("pointerdown", (ev) => {
      canvas.setPointerCapture(ev.pointerId);
      const hit = this.view.hit(ev.offsetX, ev.offsetY, this.scene);
      const moving = hit && hit.kind === "anchor" && this.tools.enabled && this.scene.selectedAnchors.has(hit.id) && !ev.shiftKey;
      drag = { x: ev.offsetX, y: ev.offsetY, moved: false, anchor: moving ? hit.id : null };
    });
    canvas.addEventListener("pointermove", (ev) => {
      if (!drag) return;
      const dx = ev.offsetX - drag.x, dy = ev.offsetY - drag.y;
      if (!drag.moved && Math.hypot(dx, dy) < 4) return;
      drag.moved = true;
      if (drag.anchor) {
        const a = this.scene.anchors.get(drag.anchor);
        const [x, y] = this.view.toWorld(ev.offsetX, ev.offsetY);
        if (a) this.scene.anchors.set(a.id, { ...a, position: { x_m: x, y_m: y }, moving: true });
        this.view.dirty = true;
        return;
      }
      this.view.pan(ev.movementX || dx, ev.movementY || dy);
      if (!ev.movementX && !ev.movementY) { drag.x = ev.offsetX; drag.y = ev.offsetY; }
    });
    canvas.addEventListener("pointerup", (ev) => {
      const d = drag;
      drag = null;
      if (!d) return;
      if (d.anchor && d.moved) {
        const [x, y] = this.view.toWorld(ev.offsetX, ev.offsetY);
        this.tools.moveAnchor(d.anchor, x, y);
        return;
      }
      if (!d.moved) this.click(ev.offsetX, ev.offsetY, ev.shiftKey);
    });
    // the map works from the keyboard too: arrows pan, + and - zoom, 0 fits the floor, Escape cancels picking
    canvas.addEventListener("keydown", (ev) => {
      const step = 40;
      const moves = { ArrowLeft: [step, 0], ArrowRight: [-step, 0], ArrowUp: [0, step], ArrowDown: [0, -step] };
      if (moves[ev.key]) this.view.pan(...moves[ev.key]);
      else if (ev.key === "+" || ev.key === "=") this.zoom(1.25);
      else if (ev.key === "-") this.zoom(1 / 1.25);
      else if (ev.key === "0") { this.view.userMoved = false; this.fitFloor(); }
      else if (ev.key === "Escape" && this.picking) {
        this.picking = false;
        canvas.classList.remove("picking");
        this.message("");
      } else return;
      ev.preventDefault();
    });
    canvas.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      this.view.zoomAt(ev.offsetX, ev.offsetY, ev.deltaY < 0 ? 1.2 : 1 / 1.2);
    }, { passive: false });
  }

  click(px, py, shift) {
    if (this.picking) {
      const [x, y] = this.view.toWorld(px, py);
      this.tools.picked(x, y);
      return;
    }
    const s = this.scene;
    if (s.drawing) {
      s.drawing.push(this.view.toWorld(px, py).map((v) => Math.round(v * 100) / 100));
      this.view.dirty = true;
      return;
    }
    const hit = this.view.hit(px, py, this.scene);
    s.selectedZone = hit || shift ? null : this.view.zoneAt(px, py, s);
    if (hit && hit.kind === "anchor" && shift) {
      s.selectedUser = null;
      if (s.selectedAnchors.has(hit.id)) s.selectedAnchors.delete(hit.id); else s.selectedAnchors.add(hit.id);
    } else {
      s.selectedUser = hit && hit.kind === "user" ? hit.id : null;
      s.selectedAnchors = new Set(hit && hit.kind === "anchor" ? [hit.id] : []);
    }
    this.tools.selectionChanged();
    this.renderDetails();
    this.view.dirty = true;
  }

  frame() {
    if (this.view.dirty && !$("live").hidden) this.view.draw(this.scene, performance.now());
    requestAnimationFrame((t) => this.frame(t));
  }
}

const dashboard = new Dashboard();
window.crowdslamDashboard = dashboard; // for the browser tests and the benchmark
dashboard.start();
