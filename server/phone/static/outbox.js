// Batches, one a second, sent in order. Each batch is sealed once (its id, its seq, its bytes, gzip-compressed
// when large and the browser can), so a retry sends the very same body: the server recognises a batch it has
// seen by (device, batch_id) and never applies it twice. While the network is down the batches wait in a
// bounded queue; past MAX_QUEUED the oldest goes, counted and said.

export const BATCH_MS = 1000;
export const MAX_QUEUED = 600; // ten minutes of batches, a few MB at most
const GZIP_ABOVE_BYTES = 1024;
const RETRY_MS = [1000, 2000, 4000, 8000];

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

async function gzip(text) {
  const stream = new Blob([text]).stream().pipeThrough(new CompressionStream("gzip"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// Why a refused batch will never be accepted, from the server's problem (RFC 9457) answer.
async function problemOf(response) {
  try {
    const p = await response.json();
    const fields = (p.errors || []).map((e) => `${e.loc}: ${e.msg}`);
    return [p.detail || p.title || `HTTP ${response.status}`, ...fields].join("; ");
  } catch {
    return `HTTP ${response.status}`;
  }
}

export class Outbox {
  // `device`: { key, buildingId, deviceId }; `takeBatch()` gives the next batch's body without ids, or null;
  // `events`: onReceipt(receipt), onRefused(text, status), onState(), onUnauthorized(text).
  constructor(device, takeBatch, events) {
    this.device = device;
    this.takeBatch = takeBatch;
    this.events = events;
    // a page load is an install: its seq starts at 0 and its batch ids cannot meet an earlier load's
    this.installMs = Date.now();
    this.seq = 0;
    this.queue = [];
    this.sending = false;
    this.stopped = true;
    this.offline = false;
    this.failures = 0;
    this.stats = { sent: 0, applied: 0, duplicates: 0, late: 0, refused: 0, lost: 0, bytes: 0, since: performance.now() };
    this.gzip = typeof CompressionStream === "function";
  }

  start() {
    if (!this.stopped) return;
    this.stopped = false;
    if (!this.stats.sent) this.stats.since = performance.now();
    this.timer = setInterval(() => this.seal(), BATCH_MS);
  }

  // Seal what the sensors gathered, then stop sealing; what is queued still goes.
  async stop() {
    clearInterval(this.timer);
    this.stopped = true;
    await this.seal();
  }

  // Seals run one after another: a batch compressed faster than the one before it must not overtake it (its
  // seq would be applied first and the earlier batch answered late).
  seal() {
    this.sealing = (this.sealing || Promise.resolve())
      .then(() => this.sealNext())
      .catch((err) => this.events.onRefused(`it could not be prepared (${err.message})`, 0));
    return this.sealing;
  }

  async sealNext() {
    const body = this.takeBatch();
    if (!body) return;
    const seq = this.seq++;
    const batch = {
      building_id: this.device.buildingId,
      device_id: this.device.deviceId,
      batch_id: `${this.device.deviceId.slice(0, 36)}-${this.installMs}-${seq}`,
      seq,
      install_ms: this.installMs,
      ...body,
    };
    const text = JSON.stringify(batch);
    const compress = this.gzip && text.length > GZIP_ABOVE_BYTES;
    const bytes = compress ? await gzip(text) : new TextEncoder().encode(text);
    if (this.queue.length >= MAX_QUEUED) {
      // the oldest waiting batch goes (never the one being sent): the phone has been offline for ten minutes
      this.queue.splice(this.sending ? 1 : 0, 1);
      this.stats.lost += 1;
    }
    this.queue.push({ id: batch.batch_id, seq, bytes, gzip: compress });
    this.events.onState();
    this.pump();
  }

  async pump() {
    if (this.sending) return;
    this.sending = true;
    try {
      while (this.queue.length && !this.unauthorized) {
        const item = this.queue[0];
        const outcome = await this.send(item);
        if (outcome === "retry") {
          this.offline = true;
          this.events.onState();
          await sleep(this.retryAfter ?? RETRY_MS[Math.min(this.failures++, RETRY_MS.length - 1)]);
          this.retryAfter = null;
          continue;
        }
        this.failures = 0;
        this.offline = false;
        if (this.queue[0] === item) this.queue.shift();
        this.events.onState();
      }
    } finally {
      this.sending = false;
    }
  }

  async send(item) {
    const headers = {
      Authorization: `Bearer ${this.device.key}`,
      "Content-Type": "application/json",
      Accept: "application/json",
    };
    if (item.gzip) headers["Content-Encoding"] = "gzip";
    const url = `/v1/buildings/${encodeURIComponent(this.device.buildingId)}/batches`;
    let response;
    try {
      response = await fetch(url, { method: "POST", headers, body: item.bytes, cache: "no-store" });
    } catch {
      return "retry"; // no answer: it may or may not have arrived, and the same id says which
    }
    this.stats.sent += 1;
    this.stats.bytes += item.bytes.length;
    if (response.ok) {
      const receipt = await response.json();
      if (receipt.status === "applied") this.stats.applied += 1;
      else if (receipt.status === "duplicate") this.stats.duplicates += 1;
      else this.stats.late += 1;
      this.events.onReceipt(receipt);
      return "done";
    }
    if (response.status === 429 || response.status === 408 || response.status >= 500) {
      const after = Number(response.headers.get("Retry-After"));
      if (after > 0) this.retryAfter = Math.min(after, 60) * 1000;
      return "retry";
    }
    const text = await problemOf(response);
    if (response.status === 401) {
      this.unauthorized = true;
      this.events.onUnauthorized(text);
      return "retry";
    }
    // refused for what it holds: sending it again would be refused again
    this.stats.refused += 1;
    this.events.onRefused(text, response.status);
    return "done";
  }

  // Bytes sent a minute, over the time since the first batch.
  bytesPerMinute() {
    const minutes = (performance.now() - this.stats.since) / 60000;
    return minutes > 0 ? this.stats.bytes / minutes : 0;
  }
}
