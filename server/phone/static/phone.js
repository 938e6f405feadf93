// The phone page: a device key from the link's fragment, the building's plan, the phone's motion sensors sent
// as one batch a second, and the server's estimate of this phone drawn with its 95 % ring. It is an ordinary
// client of the public API: what it may do is what its device key may do.

import { Api, ProblemError } from "/dashboard/assets/api.js";
import { MapView, ellipse, moveTo, person } from "/dashboard/assets/map.js";
import { MotionSensors, SENSOR_ROLES } from "./sensors.js";
import { BATCH_MS, Outbox } from "./outbox.js";
import { TagScanner, canScan, tagReading } from "./tags.js";

const STORE = "crowdslam.phone"; // the only thing kept: { key, building }
const TRAIL_POINTS = 120;
const FINGER_PX = 20; // a tap is this imprecise: the fix's sigma is at least this on the plan's scale
const MIN_FIX_SIGMA_M = 2;
const FOLLOW_AFTER_TOUCH_MS = 10000;

const $ = (id) => document.getElementById(id);
const root = $("app");

function message(text, kind = "error") {
  const el = $("message");
  el.textContent = text;
  el.className = `message ${text ? kind : ""}`;
}

class PhonePage {
  constructor() {
    this.view = new MapView($("map"));
    this.scene = {
      users: new Map(), anchors: new Map(), encounters: [], floor: 0, plan: null, extent: null, overlay: null,
      geo: null, selectedUser: null, selectedAnchors: new Set(), newestMs: 0, zones: new Map(), drawing: null,
    };
    this.chosenFloor = null; // a floor the user picked; else the estimate's
    this.touchedMs = 0; // the map follows the estimate unless the user moved it lately
    this.landmarks = [];
    this.picking = false;
    this.sensors = new MotionSensors((name, state) => this.sensorState(name, state));
    this.sensorStates = new Map();
    this.scanner = new TagScanner($("camera"));
    this.bind();
    const frame = () => {
      if (this.view.dirty) this.view.draw(this.scene, Date.now());
      requestAnimationFrame(frame);
    };
    requestAnimationFrame(frame);
    window.crowdslamPhone = this; // for the browser tests: where a point of the plan is on screen
  }

  bind() {
    $("link-form").addEventListener("submit", (ev) => {
      ev.preventDefault();
      const text = $("link-input").value.trim();
      const hash = text.includes("#") ? text.slice(text.indexOf("#") + 1) : "";
      const fragment = new URLSearchParams(hash);
      if (!fragment.get("key") || !fragment.get("building")) {
        $("welcome-message").textContent = "That is not a phone link: it has no #key=…&building=… part.";
        return;
      }
      this.open(fragment.get("key"), fragment.get("building"));
    });
    $("start").addEventListener("click", () => this.start());
    $("stop").addEventListener("click", () => this.stop());
    $("here").addEventListener("click", () => this.pick(!this.picking));
    $("pick-cancel").addEventListener("click", () => this.pick(false));
    $("scan").addEventListener("click", () => this.scan());
    $("forget").addEventListener("click", () => this.forget());
    document.addEventListener("visibilitychange", () => this.visibility());
    // another phone link opened in this tab (the page is not loaded again for a new fragment)
    window.addEventListener("hashchange", () => { if (location.hash.includes("key=")) this.stop().then(() => this.boot()); });
    $("floor").addEventListener("change", () => {
      this.chosenFloor = Number($("floor").value);
      this.showFloor(this.chosenFloor);
    });
    const canvas = $("map");
    let drag = null;
    const touches = new Map();
    canvas.addEventListener("pointerdown", (ev) => {
      this.touchedMs = Date.now();
      canvas.setPointerCapture(ev.pointerId);
      touches.set(ev.pointerId, [ev.offsetX, ev.offsetY]);
      drag = { x: ev.offsetX, y: ev.offsetY, moved: touches.size > 1 };
    });
    canvas.addEventListener("pointermove", (ev) => {
      const before = touches.get(ev.pointerId);
      if (!before || !drag) return;
      if (touches.size === 2) {
        // pinch: the distance between the two fingers scales the plan about their middle
        const [other] = [...touches.entries()].filter(([id]) => id !== ev.pointerId).map(([, p]) => p);
        const d0 = Math.hypot(before[0] - other[0], before[1] - other[1]);
        const d1 = Math.hypot(ev.offsetX - other[0], ev.offsetY - other[1]);
        if (d0 > 0) this.view.zoomAt((ev.offsetX + other[0]) / 2, (ev.offsetY + other[1]) / 2, d1 / d0);
        drag.moved = true;
      } else {
        const dx = ev.offsetX - before[0], dy = ev.offsetY - before[1];
        if (drag.moved || Math.hypot(ev.offsetX - drag.x, ev.offsetY - drag.y) >= 6) {
          drag.moved = true;
          this.view.pan(dx, dy);
        }
      }
      touches.set(ev.pointerId, [ev.offsetX, ev.offsetY]);
    });
    const end = (ev) => {
      touches.delete(ev.pointerId);
      if (drag && !drag.moved && touches.size === 0 && this.picking) this.placeHere(ev.offsetX, ev.offsetY);
      if (touches.size === 0) drag = null;
    };
    canvas.addEventListener("pointerup", end);
    canvas.addEventListener("pointercancel", (ev) => { touches.delete(ev.pointerId); drag = null; });
    canvas.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      this.touchedMs = Date.now();
      this.view.zoomAt(ev.offsetX, ev.offsetY, ev.deltaY < 0 ? 1.2 : 1 / 1.2);
    }, { passive: false });
  }

  // ------------------------------------------------------------------ the key
  async boot() {
    const fragment = new URLSearchParams(location.hash.slice(1));
    if (fragment.get("key") && fragment.get("building")) {
      const key = fragment.get("key"), building = fragment.get("building");
      history.replaceState(null, "", location.pathname); // the key leaves the address bar and the history
      await this.open(key, building);
      return;
    }
    let stored = null;
    try {
      stored = JSON.parse(localStorage.getItem(STORE) || "null");
    } catch {
      stored = null;
    }
    if (stored && stored.key && stored.building) await this.open(stored.key, stored.building);
    else this.welcome("");
  }

  welcome(text) {
    $("phone").hidden = true;
    $("welcome").hidden = false;
    $("welcome-message").textContent = text;
    root.dataset.state = "idle";
    root.dataset.ready = "false";
  }

  async open(key, buildingId) {
    this.api = new Api(key, (err) => this.unauthorized(err.message));
    let identity, building;
    try {
      identity = await this.api.get("/v1/key");
      if (identity.scope !== "device") {
        this.welcome(`That link holds a ${identity.scope} key; this page needs a phone's device key.`);
        return;
      }
      if (identity.building_id !== buildingId) {
        this.welcome(`That key is for building "${identity.building_id}", not "${buildingId}".`);
        return;
      }
      building = await this.api.get(`/v1/buildings/${encodeURIComponent(buildingId)}`);
    } catch (err) {
      if (err instanceof ProblemError && err.status === 0) {
        // no network yet: keep the key and say so; the next load tries again
        localStorage.setItem(STORE, JSON.stringify({ key, building: buildingId }));
      } else if (err instanceof ProblemError && err.status === 401) {
        localStorage.removeItem(STORE); // a revoked or unknown key opens nothing again
      }
      this.welcome(err.message);
      return;
    }
    localStorage.setItem(STORE, JSON.stringify({ key, building: buildingId }));
    this.building = building;
    this.device = { key, buildingId, deviceId: identity.device_id };
    this.outbox = new Outbox(this.device, () => this.takeBatch(), {
      onReceipt: (r) => this.receipt(r),
      onRefused: (text) => message(`A batch was refused: ${text}`),
      onState: () => this.showLink(),
      onUnauthorized: (text) => this.unauthorized(text),
    });
    $("welcome").hidden = true;
    $("phone").hidden = false;
    $("building-name").textContent = building.name;
    $("device").textContent = `Device ${identity.device_id} in building ${building.id}.`;
    this.scene.geo = building.geo_reference;
    const levels = building.floors.length ? building.floors.map((f) => f.level) : [0];
    $("floor").replaceChildren(...levels.map((level) => {
      const f = building.floors.find((x) => x.level === level);
      return new Option(f ? `${f.name} (${level})` : `${level}`, String(level));
    }));
    $("scan").hidden = !canScan();
    try {
      this.planLevels = await this.api.get(`/v1/buildings/${encodeURIComponent(building.id)}/floor-plans`);
    } catch {
      this.planLevels = [];
    }
    await this.showFloor(levels.includes(0) ? 0 : levels[0]);
    await this.loadOwnPosition();
    this.showLink();
    root.dataset.ready = "true"; // the plan drawn and the phone's own position read
  }

  unauthorized(text) {
    if (this.outbox) this.outbox.stop();
    this.sensors.stop();
    root.dataset.state = "refused";
    $("link").dataset.state = "refused";
    $("link").textContent = "key refused";
    message(`The server refuses this phone's key (${text}). Ask the operator for a new link, and forget this one.`);
  }

  forget() {
    if ($("forget").dataset.confirm !== "1") {
      $("forget").dataset.confirm = "1";
      $("forget").textContent = "Tap again to forget";
      return;
    }
    this.stop();
    localStorage.removeItem(STORE);
    this.device = null;
    $("forget").dataset.confirm = "";
    $("forget").textContent = "Forget this phone";
    this.welcome("This phone is forgotten: the page keeps nothing.");
  }

  // ------------------------------------------------------------------ the plan
  async showFloor(level) {
    this.scene.floor = level;
    $("floor").value = String(level);
    const floor = this.building.floors.find((f) => f.level === level);
    this.scene.extent = floor && floor.width_m && floor.height_m ? [0, 0, floor.width_m, floor.height_m] : null;
    this.scene.plan = null;
    if (this.planLevels.includes(level)) {
      try {
        this.scene.plan = await this.api.get(`/v1/buildings/${encodeURIComponent(this.building.id)}/floors/${level}/plan`);
      } catch (err) {
        message(err.message);
      }
    }
    this.fit();
  }

  fit() {
    let b = null;
    const grow = (x, y) => { b = b ? [Math.min(b[0], x), Math.min(b[1], y), Math.max(b[2], x), Math.max(b[3], y)] : [x, y, x, y]; };
    if (this.scene.plan) {
      const walk = (c) => (typeof c[0] === "number" ? grow(c[0], c[1]) : c.forEach(walk));
      for (const f of this.scene.plan.features) walk(f.geometry.coordinates);
    } else if (this.scene.extent) {
      grow(this.scene.extent[0], this.scene.extent[1]);
      grow(this.scene.extent[2], this.scene.extent[3]);
    }
    this.view.userMoved = false;
    this.view.fit(b || [0, 0, 50, 50]);
  }

  // ------------------------------------------------------------------ sensing and sending
  async start() {
    message("");
    $("start").disabled = true;
    if (!await MotionSensors.askPermission()) {
      $("start").disabled = false;
      for (const name of ["accelerometer", "gyroscope", "orientation"]) this.sensorState(name, "refused");
      this.refusedMotion();
      return;
    }
    const mode = await this.sensors.start();
    root.dataset.mode = mode || "";
    if (this.sensorStates.get("accelerometer") !== "ok") {
      this.sensors.stop();
      $("start").disabled = false;
      if ([...this.sensorStates.values()].includes("refused")) this.refusedMotion();
      else message("This browser gives no motion readings: the server cannot follow this phone. A phone with an accelerometer, in Chrome or Safari, can.");
      return;
    }
    this.outbox.start();
    this.keepAwake();
    root.dataset.state = "running";
    $("start").hidden = true;
    $("start").disabled = false;
    $("stop").hidden = false;
    this.showLink();
  }

  // A phone whose screen sleeps stops its sensors and timers: while walking, the page asks to stay awake
  // (Screen Wake Lock, where offered; the lock is let go when the page is hidden, and asked again on return).
  async keepAwake() {
    if (!("wakeLock" in navigator) || root.dataset.state !== "running" || document.hidden) return;
    try {
      this.wakeLock = await navigator.wakeLock.request("screen");
    } catch {
      this.wakeLock = null; // refused (battery saver): the hint below says what that costs
    }
  }

  visibility() {
    if (root.dataset.state !== "running") return;
    if (document.hidden) {
      this.hiddenMs = Date.now();
      return;
    }
    this.keepAwake();
    if (this.hiddenMs) {
      const s = Math.round((Date.now() - this.hiddenMs) / 1000);
      message(`The page was hidden for ${s} s: the phone gives a hidden page no motion readings, so those steps `
        + "are missing. Keep the page open while you walk.", "error");
      this.hiddenMs = 0;
    }
  }

  refusedMotion() {
    root.dataset.state = "refused";
    message("Motion sensors were refused: without them the server cannot count your steps, so it cannot follow "
      + "you. Allow motion sensors for this site in the browser's settings, then tap Start again.");
  }

  async stop() {
    this.sensors.stop();
    if (this.wakeLock) this.wakeLock.release().catch(() => {});
    this.wakeLock = null;
    if (this.outbox) await this.outbox.stop();
    root.dataset.state = "idle";
    $("start").hidden = false;
    $("stop").hidden = true;
    this.showLink();
  }

  // What a batch carries: each stream's samples since the last one, and the fixes and tags since then.
  takeBatch() {
    const body = {};
    for (const [name, stream] of Object.entries(this.sensors.streams)) {
      const wire = stream.take();
      if (wire) body[name] = wire;
    }
    if (this.landmarks.length) {
      // a place tapped before Start is where the user still stands: timed within this batch, whose span the
      // server bounds (a tap minutes earlier would stretch it past a minute and have it refused)
      const earliest = Date.now() - BATCH_MS;
      body.landmarks = this.landmarks.splice(0).map((l) => ({ ...l, t_ms: Math.max(l.t_ms, earliest) }));
    }
    return Object.keys(body).length ? body : null;
  }

  sensorState(name, state) {
    this.sensorStates.set(name, state);
    root.dataset.sensors = [...this.sensorStates].map(([n, s]) => `${n}:${s}`).join(",");
    $("sensors").replaceChildren(...[...this.sensorStates].map(([n, s]) => {
      const [label, role] = SENSOR_ROLES[n];
      const li = document.createElement("li");
      li.dataset.state = s;
      li.dataset.sensor = n;
      li.textContent = s === "ok" ? label : s === "waiting" ? `${label}: starting` : `${label} ${s === "refused" ? "refused" : "missing"} (${role})`;
      return li;
    }));
  }

  showLink() {
    const o = this.outbox;
    if (!o) return;
    const link = $("link");
    if (o.unauthorized) return;
    const state = o.offline ? "offline" : o.stopped ? "idle" : "sending";
    link.dataset.state = state;
    link.textContent = state === "offline" ? `offline, ${o.queue.length} waiting` : state;
    const s = o.stats;
    Object.assign(root.dataset, {
      sent: String(s.sent), applied: String(s.applied), queued: String(o.queue.length),
      refused: String(s.refused), lost: String(s.lost), duplicates: String(s.duplicates), late: String(s.late),
    });
    const kb = o.bytesPerMinute() / 1024;
    $("stats").textContent = `${s.applied} batches applied, ${o.queue.length} waiting`
      + (s.lost ? `, ${s.lost} lost offline` : "") + (s.sent ? `; ${kb.toFixed(0)} KiB a minute` : "");
  }

  // ------------------------------------------------------------------ the start: a tap or a tag
  pick(on) {
    this.picking = on;
    $("map").classList.toggle("picking", on);
    $("picking").hidden = !on;
  }

  placeHere(px, py) {
    this.pick(false);
    const [x, y] = this.view.toWorld(px, py);
    const sigma = Math.max(MIN_FIX_SIGMA_M, FINGER_PX / this.view.scale);
    const round = (v) => Math.round(v * 100) / 100;
    this.landmarks.push({
      kind: "fix", t_ms: Date.now(), position: { x_m: round(x), y_m: round(y) },
      sigma_m: Math.min(round(sigma), 100), floor: this.scene.floor,
    });
    const within = `within ${Math.round(sigma * 10) / 10} m`;
    message(root.dataset.state === "running" ? `Your place (${within}) goes to the server with the next batch.`
      : `Your place (${within}) goes to the server once you tap Start. Zoom in to tap it closer.`, "ok");
  }

  async scan() {
    if (this.scanning) {
      this.scanning.abort();
      return;
    }
    this.scanning = new AbortController();
    $("scan").textContent = "Stop scanning";
    try {
      const text = await this.scanner.scan(this.scanning.signal);
      if (text) {
        const [reading, why] = tagReading(text, Date.now());
        if (reading) {
          this.landmarks.push(reading);
          message(`Tag ${reading.tag_id} read: it goes with the next batch.`, "ok");
        } else {
          message(why);
        }
      }
    } catch (err) {
      message(err.name === "NotAllowedError" ? "The camera was refused: tap “I am here” on the plan instead."
        : `The camera cannot scan here (${err.message}): tap “I am here” on the plan instead.`);
    } finally {
      this.scanning = null;
      $("scan").textContent = "Scan a tag";
    }
  }

  // ------------------------------------------------------------------ the estimate
  async loadOwnPosition() {
    const path = `/v1/buildings/${encodeURIComponent(this.device.buildingId)}/devices/${encodeURIComponent(this.device.deviceId)}/position`;
    try {
      this.showEstimate((await this.api.get(path)).estimate);
    } catch (err) {
      message(err.message);
      this.showEstimate(null);
    }
  }

  receipt(r) {
    if (r.estimate) this.showEstimate(r.estimate);
    else if (!r.tracking) this.showEstimate(null);
    if (r.warnings && r.warnings.length) message(r.warnings.join(" "), "ok");
  }

  showEstimate(est) {
    const placement = $("placement");
    if (!est) {
      root.dataset.placed = "false";
      placement.dataset.placed = "false";
      placement.textContent = "Not placed yet: tap “I am here”, then your place on the plan"
        + (canScan() ? ", or scan a tag." : ".");
      return;
    }
    root.dataset.placed = "true";
    placement.dataset.placed = "true";
    const e = ellipse(est.covariance_m2);
    const r95 = e.rx;
    const floorName = $("floor").querySelector(`option[value="${est.floor}"]`)?.textContent ?? String(est.floor);
    placement.textContent = `On floor ${floorName}` + (est.floor_probability < 0.995 ? ` (${Math.round(est.floor_probability * 100)} % sure)` : "")
      + `, within ${r95 < 10 ? r95.toFixed(1) : Math.round(r95)} m (95 %).`;
    root.dataset.x = est.position.x_m.toFixed(2);
    root.dataset.y = est.position.y_m.toFixed(2);
    root.dataset.estimateMs = String(est.t_ms);
    let u = this.scene.users.get(est.user_id);
    if (!u) {
      u = person(est, "#1d6fb8", TRAIL_POINTS);
      this.scene.users.clear();
      this.scene.users.set(est.user_id, u);
    }
    moveTo(u, est);
    this.scene.newestMs = est.t_ms;
    this.scene.selectedUser = est.user_id;
    if (this.chosenFloor === null && est.floor !== this.scene.floor) this.showFloor(est.floor);
    this.follow(est.position.x_m, est.position.y_m);
    this.view.dirty = true;
  }

  // Keep the estimate on screen: centred again when it nears an edge, unless the user moved the map lately.
  follow(x, y) {
    if (Date.now() - this.touchedMs < FOLLOW_AFTER_TOUCH_MS) return;
    const canvas = $("map");
    const w = canvas.clientWidth, h = canvas.clientHeight;
    const [sx, sy] = this.view.toScreen(x, y);
    if (sx > 0.2 * w && sx < 0.8 * w && sy > 0.2 * h && sy < 0.8 * h) return;
    this.view.pan(w / 2 - sx, h / 2 - sy);
  }
}

new PhonePage().boot();
