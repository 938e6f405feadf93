// Replaying the last hour: the slider picks a time, the server answers each person's estimate then
// (GET .../positions?at_ms=). While it is on, live updates are not drawn; they go on arriving.

import { fmtTime } from "./format.js";

const HOUR_S = 3600;
const PLAY_STEP_S = 2; // eight times real time
const PLAY_EVERY_MS = 250;

export class History {
  constructor(app) {
    this.app = app;
    this.active = false;
    this.endMs = 0;
    this.timer = null;
    this.pending = null;
    this.playing = false;
    this.toggle = document.getElementById("live-toggle");
    this.slider = document.getElementById("history");
    this.label = document.getElementById("history-time");
    this.play = document.getElementById("play");
    this.toggle.addEventListener("change", () => (this.toggle.checked ? this.stop() : this.begin()));
    this.slider.addEventListener("input", () => this.schedule());
    this.play.addEventListener("click", () => (this.playing ? this.pause() : this.startPlaying()));
  }

  begin() {
    // the hour ends at the newest estimate the building holds (phones' clocks, not this browser's)
    this.endMs = this.app.scene.newestMs || Date.now();
    this.active = true;
    this.slider.disabled = false;
    this.play.disabled = false;
    this.slider.max = String(HOUR_S);
    this.slider.value = String(HOUR_S);
    this.app.scene.encounters = [];
    this.show(this.atMs(), false);
  }

  stop() {
    this.pause();
    const was = this.active;
    this.active = false;
    this.toggle.checked = true;
    this.slider.disabled = true;
    this.play.disabled = true;
    this.label.textContent = "live";
    if (was && this.app.api && this.app.building) {
      this.app.scene.users.clear();
      this.app.loadPositions();
    }
  }

  atMs() { return this.endMs - (HOUR_S - Number(this.slider.value)) * 1000; }

  schedule() {
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.show(this.atMs(), false), 120);
  }

  async show(atMs, trail) {
    this.label.textContent = fmtTime(atMs);
    const request = (this.pending = this.app.api.get(this.app.path(`/positions?at_ms=${Math.round(atMs)}&window_ms=30000`)));
    let estimates;
    try {
      estimates = await request;
    } catch (err) {
      this.app.problem(err);
      return;
    }
    if (request !== this.pending || !this.active) return; // a later position of the slider won
    const users = this.app.scene.users;
    if (trail) { // playing: people keep their trails; those not heard from then leave
      const seen = new Set(estimates.map((e) => e.user_id));
      for (const id of [...users.keys()]) if (!seen.has(id)) users.delete(id);
    } else {
      users.clear();
    }
    this.app.scene.newestMs = 0;
    for (const e of estimates) this.app.updateUser(e, trail);
    this.app.published();
  }

  startPlaying() {
    this.playing = true;
    this.play.textContent = "❚❚";
    const step = async () => {
      if (!this.playing) return;
      const next = Math.min(HOUR_S, Number(this.slider.value) + PLAY_STEP_S);
      this.slider.value = String(next);
      await this.show(this.atMs(), true);
      if (next >= HOUR_S) this.pause();
      else if (this.playing) this.timer = setTimeout(step, PLAY_EVERY_MS);
    };
    step();
  }

  pause() {
    this.playing = false;
    clearTimeout(this.timer);
    this.play.textContent = "▶";
  }
}
