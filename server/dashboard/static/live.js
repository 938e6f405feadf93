// The building's live socket. The key travels as a subprotocol (browsers cannot set a WebSocket's headers,
// and a query string lands in access logs). A dropped socket reconnects with capped exponential backoff;
// a refused key (close code 4401) does not.

const MAX_DELAY_MS = 15000;

export class LiveSocket {
  constructor({ buildingId, key, onMessages, onState, onRefused }) {
    this.buildingId = buildingId;
    this.key = key;
    this.onMessages = onMessages;
    this.onState = onState;
    this.onRefused = onRefused;
    this.attempt = 0;
    this.ws = null;
    this.timer = null;
    this.stopped = false;
    this.wasOpen = false;
  }

  start() {
    this.stopped = false;
    this.connect();
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
    if (this.ws) {
      this.ws.onclose = null;
      this.ws.close(1000, "dashboard closed");
      this.ws = null;
    }
  }

  connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const url = `${scheme}://${location.host}/v1/buildings/${encodeURIComponent(this.buildingId)}/live?batch=true`;
    this.onState("connecting", this.attempt ? `attempt ${this.attempt + 1}` : "");
    const ws = new WebSocket(url, ["crowdslam.live", `bearer.${this.key}`]);
    this.ws = ws;
    ws.onopen = () => {
      const reconnected = this.wasOpen;
      this.attempt = 0;
      this.wasOpen = true;
      this.onState("connected", "", reconnected);
    };
    ws.onmessage = (event) => {
      let message;
      try {
        message = JSON.parse(event.data);
      } catch {
        return;
      }
      this.onMessages(message.type === "batch" ? message.messages : [message]);
    };
    ws.onclose = (event) => {
      this.ws = null;
      if (this.stopped) return;
      if (event.code === 4401) {
        this.onRefused(event.reason || "the key was refused");
        return;
      }
      if (event.code === 4403 || event.code === 4404) {
        this.onState("refused", event.reason || `refused (${event.code})`);
        return;
      }
      const delay = Math.min(MAX_DELAY_MS, 500 * 2 ** this.attempt) * (0.75 + 0.5 * Math.random());
      this.attempt += 1;
      this.onState("reconnecting", `disconnected; retrying in ${(delay / 1000).toFixed(1)} s`);
      this.timer = setTimeout(() => this.connect(), delay);
    };
  }
}
