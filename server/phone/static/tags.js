// A tag's QR code read by the camera, where the browser has BarcodeDetector, as the batch's tag reading. A
// payload of the form "#<id> <lat>,<lon> z<floor>" places the phone by itself; any other payload names a tag
// the building's operator placed (its id, the payload's letters, digits and ._:- up to 64).

const IDENTIFIER = /^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$/;

export const canScan = () => "BarcodeDetector" in globalThis && !!(navigator.mediaDevices && navigator.mediaDevices.getUserMedia);

// The tag reading for a QR code's text, or null (with why) when it names no tag.
export function tagReading(text, tMs) {
  const payload = text.trim();
  if (payload.startsWith("#")) {
    const id = payload.slice(1).split(/\s+/)[0];
    if (!IDENTIFIER.test(id)) return [null, `the tag's id "${id.slice(0, 20)}" is not one this server reads`];
    return [{ kind: "tag", t_ms: Math.round(tMs), tag_id: id, payload: payload.slice(0, 256) }, ""];
  }
  if (!IDENTIFIER.test(payload)) return [null, "this QR code is not a building tag"];
  return [{ kind: "tag", t_ms: Math.round(tMs), tag_id: payload }, ""];
}

export class TagScanner {
  constructor(video) {
    this.video = video;
    this.stream = null;
  }

  // The first QR code seen, as its text; rejects when the camera is refused or absent.
  async scan(signal) {
    const detector = new BarcodeDetector({ formats: ["qr_code"] });
    this.stream = await navigator.mediaDevices.getUserMedia({ video: { facingMode: "environment" }, audio: false });
    try {
      this.video.srcObject = this.stream;
      this.video.hidden = false;
      await this.video.play();
      while (!signal.aborted) {
        const codes = await detector.detect(this.video);
        if (codes.length) return codes[0].rawValue;
        await new Promise((resolve) => setTimeout(resolve, 200));
      }
      return null;
    } finally {
      this.close();
    }
  }

  close() {
    if (this.stream) for (const track of this.stream.getTracks()) track.stop();
    this.stream = null;
    this.video.srcObject = null;
    this.video.hidden = true;
  }
}
