// Phone links: an operator mints a device key for one phone and shows its link to the phone page as a QR
// code, which the phone's camera opens. The key is in the link's fragment, which browsers never send.

import qrcode from "./vendor/qrcode.mjs";

const $ = (id) => document.getElementById(id);
const QR_PX = 4; // per module: a link of ~120 characters is a 57-module code, 228 px plus its quiet zone

export function phoneLink(origin, key, buildingId) {
  const fragment = new URLSearchParams({ key, building: buildingId });
  return `${origin}/phone/#${fragment}`;
}

// The QR code of `text` on a canvas, with the four-module quiet zone scanners need.
export function drawQr(canvas, text) {
  const qr = qrcode(0, "M");
  qr.addData(text);
  qr.make();
  const n = qr.getModuleCount(), quiet = 4;
  canvas.width = canvas.height = (n + 2 * quiet) * QR_PX;
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#ffffff";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#000000";
  for (let r = 0; r < n; r++) {
    for (let c = 0; c < n; c++) if (qr.isDark(r, c)) ctx.fillRect((c + quiet) * QR_PX, (r + quiet) * QR_PX, QR_PX, QR_PX);
  }
  return n;
}

export class PhoneLinks {
  constructor(tools) {
    this.tools = tools;
    $("phone-form").addEventListener("submit", (ev) => { ev.preventDefault(); this.mint(); });
    $("phone-copy").addEventListener("click", () => this.copy());
  }

  async mint() {
    const app = this.tools.app;
    const typed = $("phone-device").value.trim();
    const deviceId = typed || `phone-${crypto.getRandomValues(new Uint32Array(1))[0].toString(16).padStart(8, "0")}`;
    const created = await this.tools.act(
      () => app.api.post(app.path("/keys"), { scope: "device", device_id: deviceId }),
      (k) => `Device key ${k.prefix} minted for ${k.device_id}: scan the code with that phone.`,
    );
    if (!created) return;
    this.link = phoneLink(location.origin, created.key, created.building_id);
    drawQr($("phone-qr"), this.link);
    $("phone-link").textContent = this.link;
    $("phone-result").hidden = false;
    $("phone-result").dataset.device = created.device_id;
    $("phone-device").value = "";
    if (location.protocol !== "https:" && !["localhost", "127.0.0.1", "[::1]"].includes(location.hostname)) {
      $("phone-note").textContent = "Phones give motion sensors only to HTTPS pages: serve this server over HTTPS "
        + "(crowdslam serve --tls-self-signed for a trial) and open the dashboard by that address.";
    } else {
      $("phone-note").textContent = "The link holds the phone's key: show it to that phone only. Revoke the key below to end it.";
    }
  }

  async copy() {
    if (!this.link) return;
    try {
      await navigator.clipboard.writeText(this.link);
      this.tools.ok("The phone link is copied.");
    } catch {
      this.tools.app.message("This browser does not let the page copy; select the link instead.");
    }
  }
}
