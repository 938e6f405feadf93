// Operator tools: pin, move, delete and merge anchors; draw, redraw and delete zones; upload a floor plan; start a signal-map build and
// watch it; list and revoke keys. Each goes through the public REST API; a refusal shows its Problem.

import { ANCHOR_STYLE } from "./map.js";
import { PhoneLinks } from "./phones.js";

const $ = (id) => document.getElementById(id);
const BUILD_POLL_MS = 2000;

export class OperatorTools {
  constructor(app) {
    this.app = app;
    this.enabled = false;
    $("pin-type").replaceChildren(...Object.keys(ANCHOR_STYLE).map((t) => new Option(t, t)));
    $("pin-form").addEventListener("submit", (ev) => { ev.preventDefault(); this.pin(); });
    $("pin-pick").addEventListener("click", () => this.pick());
    $("anchor-delete").addEventListener("click", () => this.confirmThen($("anchor-delete"), () => this.deleteSelected()));
    $("anchor-merge").addEventListener("click", () => this.merge());
    $("plan-form").addEventListener("submit", (ev) => { ev.preventDefault(); this.uploadPlan(); });
    $("zone-draw").addEventListener("click", () => this.drawZone());
    $("zone-cancel").addEventListener("click", () => this.endDrawing(""));
    $("zone-form").addEventListener("submit", (ev) => { ev.preventDefault(); this.saveZone(); });
    $("zone-delete").addEventListener("click", () => this.confirmThen($("zone-delete"), () => this.deleteZone()));
    $("build-start").addEventListener("click", () => this.startBuild());
    $("keys-card").addEventListener("toggle", () => { if ($("keys-card").open) this.loadKeys(); });
    this.phones = new PhoneLinks(this);
  }

  show(enabled) {
    this.enabled = enabled;
    $("tools").hidden = !enabled;
    this.selectionChanged();
  }

  ok(text) { this.app.message(text, "ok"); }

  async act(action, success) {
    try {
      const result = await action();
      if (success) this.ok(success(result));
      return result;
    } catch (err) {
      this.app.problem(err);
      return undefined;
    }
  }

  // A destructive button asks once more on its own face, not in a dialog.
  confirmThen(button, action) {
    if (button.dataset.confirm === "1") {
      button.dataset.confirm = "";
      button.textContent = button.dataset.label;
      action();
      return;
    }
    button.dataset.label = button.textContent;
    button.dataset.confirm = "1";
    button.textContent = "Click again to confirm";
    setTimeout(() => {
      if (button.dataset.confirm === "1") { button.dataset.confirm = ""; button.textContent = button.dataset.label; }
    }, 4000);
  }

  selectionChanged() {
    const n = this.app.scene.selectedAnchors.size;
    $("anchor-delete").disabled = !this.enabled || n === 0;
    $("anchor-merge").disabled = !this.enabled || n < 2;
    $("zone-delete").disabled = !this.enabled || !this.app.scene.selectedZone;
    const drawing = Boolean(this.app.scene.drawing);
    $("zone-finish").disabled = !this.enabled || !drawing;
    $("zone-cancel").disabled = !drawing;
  }

  // A zone is drawn corner by corner on the map, then saved on the floor shown (a zone selected is
  // redrawn under its own id).
  drawZone() {
    this.app.scene.drawing = [];
    this.selectionChanged();
    this.app.message("Click the map at each corner of the zone, then Save zone.", "ok");
  }

  endDrawing(text) {
    this.app.scene.drawing = null;
    this.app.view.dirty = true;
    this.selectionChanged();
    this.app.message(text, "ok");
  }

  async saveZone() {
    const s = this.app.scene;
    const corners = s.drawing || [];
    if (corners.length < 3) {
      this.app.message("A zone needs at least three corners.");
      return;
    }
    const name = $("zone-name").value.trim();
    const id = s.selectedZone || name.toLowerCase().replace(/[^a-z0-9._:-]+/g, "-").replace(/^[^a-z0-9]+/, "").slice(0, 64) || `zone-${Date.now()}`;
    const dwell = $("zone-dwell").value ? Number($("zone-dwell").value) : null;
    const body = {
      floor: s.floor, name, dwell_s: dwell,
      polygon: { type: "Polygon", coordinates: [[...corners, corners[0]]] },
    };
    const zone = await this.act(() => this.app.api.put(this.app.path(`/zones/${encodeURIComponent(id)}`), body));
    if (!zone) return;
    s.zones.set(zone.id, zone);
    this.app.publishZones();
    this.endDrawing(`Saved zone ${zone.id}.`);
  }

  async deleteZone() {
    const id = this.app.scene.selectedZone;
    if (!id) return;
    const done = await this.act(() => this.app.api.del(this.app.path(`/zones/${encodeURIComponent(id)}`)), () => `Deleted zone ${id}.`);
    if (done === undefined) return;
    this.app.scene.zones.delete(id);
    this.app.scene.selectedZone = null;
    this.app.publishZones();
    this.app.refresh();
  }

  pick() {
    this.app.picking = true;
    $("map").classList.add("picking");
    this.app.message("Click the map where the anchor is.", "ok");
  }

  picked(x, y) {
    this.app.picking = false;
    $("map").classList.remove("picking");
    $("pin-x").value = x.toFixed(2);
    $("pin-y").value = y.toFixed(2);
    this.app.message("");
  }

  anchorBody(floor, type, x, y, label) {
    return { floor, type, position: { x_m: x, y_m: y }, label: label || null };
  }

  async pin() {
    const label = $("pin-label").value.trim();
    const id = `pin-${Date.now().toString(36)}`;
    const body = this.anchorBody(this.app.scene.floor, $("pin-type").value, Number($("pin-x").value), Number($("pin-y").value), label);
    const anchor = await this.act(() => this.app.api.put(this.app.path(`/anchors/${id}`), body), (a) => `Pinned ${a.type} anchor ${a.id}.`);
    if (anchor) {
      this.app.scene.anchors.set(anchor.id, anchor);
      this.app.scene.selectedAnchors = new Set([anchor.id]);
      this.app.refresh();
    }
  }

  async moveAnchor(id, x, y) {
    const a = this.app.scene.anchors.get(id);
    const body = this.anchorBody(a.floor, a.type, x, y, a.label);
    const anchor = await this.act(() => this.app.api.put(this.app.path(`/anchors/${encodeURIComponent(id)}`), body), (m) => `Moved ${m.id}; it is now pinned there.`);
    if (anchor) this.app.scene.anchors.set(anchor.id, anchor);
    else await this.app.loadAnchors(); // refused: back where the server has it
    this.app.refresh();
  }

  async deleteSelected() {
    for (const id of [...this.app.scene.selectedAnchors]) {
      const done = await this.act(() => this.app.api.del(this.app.path(`/anchors/${encodeURIComponent(id)}`)), () => `Deleted ${id}.`);
      if (done === null) this.app.scene.anchors.delete(id);
    }
    this.app.scene.selectedAnchors = new Set();
    this.app.refresh();
  }

  async merge() {
    const ids = [...this.app.scene.selectedAnchors];
    const merged = await this.act(() => this.app.api.post(this.app.path("/anchors:merge"), { anchor_ids: ids }), (a) => `Merged ${ids.length} anchors into ${a.id}.`);
    if (merged) {
      for (const id of ids) this.app.scene.anchors.delete(id);
      this.app.scene.anchors.set(merged.id, merged);
      this.app.scene.selectedAnchors = new Set([merged.id]);
      this.app.refresh();
    }
  }

  async uploadPlan() {
    const file = $("plan-file").files[0];
    if (!file) return;
    let text;
    try {
      text = await file.text();
      JSON.parse(text);
    } catch (err) {
      this.app.message(`${file.name} is not JSON: ${err.message}`);
      return;
    }
    const level = this.app.scene.floor;
    const plan = await this.act(() => this.app.api.put(this.app.path(`/floors/${level}/plan`), text), () => `Floor ${level}'s plan uploaded.`);
    if (plan) {
      await this.app.loadFloor();
      this.app.view.userMoved = false;
      this.app.fitFloor();
    }
  }

  async startBuild() {
    const job = await this.act(() => this.app.api.post(this.app.path("/signal-maps")), (j) => `Signal-map build ${j.id} ${j.status}.`);
    if (!job) return;
    $("build-start").disabled = true;
    const poll = async () => {
      let current;
      try {
        current = await this.app.api.get(this.app.path(`/signal-maps/${job.id}`));
      } catch (err) {
        this.app.problem(err);
        $("build-start").disabled = false;
        return;
      }
      $("build-status").textContent = `build ${current.id}: ${current.status}${current.error ? ` (${current.error})` : ""}`;
      if (current.status === "queued" || current.status === "running") {
        setTimeout(poll, BUILD_POLL_MS);
        return;
      }
      $("build-start").disabled = false;
      if (current.status === "done") {
        this.ok(`Build ${current.id} done: ${current.files.length} files; choose a map under "Signal map".`);
        await this.app.loadOverlays();
      } else {
        this.app.message(`Build ${current.id} failed: ${current.error}`);
      }
    };
    poll();
  }

  async loadKeys() {
    const keys = await this.act(() => this.app.api.get(this.app.path("/keys")));
    if (!keys) return;
    const body = $("keys").tBodies[0];
    body.replaceChildren(...keys.filter((k) => !k.revoked_at).map((k) => {
      const tr = document.createElement("tr");
      for (const v of [k.prefix, k.scope, k.device_id || "", k.last_used_at ? k.last_used_at.slice(0, 16).replace("T", " ") : "never"]) {
        const td = document.createElement("td");
        td.textContent = v;
        tr.append(td);
      }
      const td = document.createElement("td");
      const revoke = document.createElement("button");
      revoke.type = "button";
      revoke.className = "danger";
      revoke.textContent = "Revoke";
      revoke.dataset.prefix = k.prefix;
      revoke.addEventListener("click", () => this.confirmThen(revoke, async () => {
        const done = await this.act(() => this.app.api.del(this.app.path(`/keys/${encodeURIComponent(k.prefix)}`)), () => `Key ${k.prefix} revoked.`);
        if (done === null) tr.remove();
      }));
      td.append(revoke);
      tr.append(td);
      return tr;
    }));
  }
}
