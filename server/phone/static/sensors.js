// The phone's motion sensors as the batch's streams, in Android's SensorEvent conventions (the phone frame,
// m/s^2 with gravity, rad/s, microtesla, and the rotation vector as the device-to-east-north-up quaternion).
// The Generic Sensor API first (Accelerometer, Gyroscope, AbsoluteOrientationSensor, Magnetometer where
// offered); DeviceMotionEvent and DeviceOrientationEvent where it is absent, refused or silent. At most
// RATE_HZ samples a second per stream, at the browser's own timestamps (epoch milliseconds).

export const RATE_HZ = 50;
const PERIOD_MS = 1000 / RATE_HZ;
const SILENT_MS = 2500; // a Generic Sensor that started but gives nothing in this long is taken as absent
const DEG = Math.PI / 180;

// What each sensor costs the phone when it is missing, said to the user as it is.
export const SENSOR_ROLES = {
  accelerometer: ["Accelerometer", "steps: without it the server cannot follow this phone at all"],
  gyroscope: ["Gyroscope", "turns: without it the direction of each step is noisier"],
  orientation: ["Orientation", "direction: without it steps carry only turns, and the start needs a direction"],
  magnetometer: ["Magnetometer", "magnetic anchors: the building's magnetic signatures go unused"],
};

// One stream's columns, with the 50 Hz cap and strictly increasing integer times the API requires.
export class Stream {
  constructor(columns) {
    this.columns = columns;
    this.clear();
    this.next = -Infinity;
    this.last = -Infinity;
  }

  clear() {
    this.t = [];
    this.values = this.columns.map(() => []);
  }

  push(tMs, values, digits) {
    const t = Math.round(tMs);
    if (t < this.next - 1 || t <= this.last) return false;
    // the next sample is due a period after this one; a late one does not make the following ones early
    this.next = t - this.next > PERIOD_MS ? t + PERIOD_MS : this.next + PERIOD_MS;
    this.last = t;
    this.t.push(t);
    const scale = 10 ** digits;
    values.forEach((v, i) => this.values[i].push(Math.round(v * scale) / scale));
    return true;
  }

  get length() { return this.t.length; }

  // The wire object (and the stream emptied), or null with no samples.
  take() {
    if (!this.t.length) return null;
    const out = { t_ms: this.t };
    this.columns.forEach((name, i) => { out[name] = this.values[i]; });
    this.clear();
    return out;
  }
}

// W3C DeviceOrientation's Z-X'-Y'' Euler angles (degrees) as the device-to-earth quaternion [x, y, z, w].
export function quaternionFromEuler(alpha, beta, gamma) {
  const x = (beta || 0) * DEG / 2, y = (gamma || 0) * DEG / 2, z = (alpha || 0) * DEG / 2;
  const cX = Math.cos(x), cY = Math.cos(y), cZ = Math.cos(z);
  const sX = Math.sin(x), sY = Math.sin(y), sZ = Math.sin(z);
  return [
    sX * cY * cZ - cX * sY * sZ,
    cX * sY * cZ + sX * cY * sZ,
    cX * cY * sZ + sX * sY * cZ,
    cX * cY * cZ - sX * sY * sZ,
  ];
}

// Up, in the phone's frame, for W3C Euler angles: what an accelerometer at rest reads, divided by g.
function upInDevice(beta, gamma) {
  const b = beta * DEG, g = gamma * DEG;
  return [-Math.cos(b) * Math.sin(g), Math.sin(b), Math.cos(b) * Math.cos(g)];
}

const epochMs = (domTimestamp) => performance.timeOrigin + domTimestamp;

// The motion sources, started on a user's tap. `onState(name, state, detail)` reports each sensor as
// "waiting", "ok", "missing" or "refused"; samples accumulate in `streams` until the batcher takes them.
export class MotionSensors {
  constructor(onState) {
    this.onState = onState;
    this.streams = {
      accelerometer: new Stream(["x", "y", "z"]),
      gyroscope: new Stream(["x", "y", "z"]),
      magnetometer: new Stream(["x", "y", "z"]),
      rotation_vector: new Stream(["x", "y", "z", "w"]),
      game_rotation_vector: new Stream(["x", "y", "z", "w"]),
    };
    this.generic = [];
    this.listeners = [];
    this.mode = null;
    this.timer = null;
    this.refused = false;
  }

  // Motion access asked on a tap where the browser asks for it (iOS, recent Chromium); elsewhere this resolves
  // at once. False: refused.
  static async askPermission() {
    const asks = [globalThis.DeviceMotionEvent, globalThis.DeviceOrientationEvent]
      .filter((c) => c && typeof c.requestPermission === "function");
    for (const c of asks) {
      let answer;
      try {
        answer = await c.requestPermission();
      } catch {
        answer = "denied";
      }
      if (answer !== "granted") return false;
    }
    return true;
  }

  async start() {
    const generic = "Accelerometer" in globalThis && "Gyroscope" in globalThis;
    if (generic && await this.startGeneric()) return this.mode;
    this.stopGeneric();
    await this.startEvents();
    return this.mode;
  }

  stop() {
    this.stopGeneric();
    for (const [target, type, fn] of this.listeners) target.removeEventListener(type, fn);
    this.listeners = [];
    clearTimeout(this.timer);
    this.mode = null;
  }

  // ------------------------------------------------------------------ Generic Sensor API
  // True when the accelerometer delivers readings; false (nothing kept running) to fall back to events.
  async startGeneric() {
    this.mode = "generic";
    const open = (name, make, onReading) => {
      let sensor;
      try {
        sensor = make();
      } catch (err) {
        return Promise.resolve(err.name === "SecurityError" ? "refused" : "missing");
      }
      this.generic.push(sensor);
      this.onState(name, "waiting");
      return new Promise((resolve) => {
        const timer = setTimeout(() => resolve("missing"), SILENT_MS);
        sensor.addEventListener("reading", () => {
          onReading(sensor);
          clearTimeout(timer);
          resolve("ok");
        });
        sensor.addEventListener("error", (ev) => {
          clearTimeout(timer);
          resolve(ev.error && ev.error.name === "NotAllowedError" ? "refused" : "missing");
        });
        sensor.start();
      });
    };
    const options = { frequency: RATE_HZ, referenceFrame: "device" };
    const s = this.streams;
    const vector = (stream, digits) => (sensor) => stream.push(epochMs(sensor.timestamp), [sensor.x, sensor.y, sensor.z], digits);
    const quaternion = (stream) => (sensor) => { if (sensor.quaternion) stream.push(epochMs(sensor.timestamp), sensor.quaternion, 5); };
    const absolute = "AbsoluteOrientationSensor" in globalThis;
    const relative = "RelativeOrientationSensor" in globalThis;
    const [acc, gyr, ori, mag] = await Promise.all([
      open("accelerometer", () => new Accelerometer(options), vector(s.accelerometer, 3)),
      open("gyroscope", () => new Gyroscope(options), vector(s.gyroscope, 4)),
      absolute ? open("orientation", () => new AbsoluteOrientationSensor(options), quaternion(s.rotation_vector))
        : relative ? open("orientation", () => new RelativeOrientationSensor(options), quaternion(s.game_rotation_vector))
          : Promise.resolve("missing"),
      "Magnetometer" in globalThis ? open("magnetometer", () => new Magnetometer(options), vector(s.magnetometer, 2))
        : Promise.resolve("missing"),
    ]);
    if (acc !== "ok") {
      this.refused = acc === "refused"; // the events fall back on the same permission
      return false;
    }
    this.onState("accelerometer", "ok");
    this.onState("gyroscope", gyr);
    this.onState("orientation", ori);
    this.onState("magnetometer", mag);
    return true;
  }

  stopGeneric() {
    for (const sensor of this.generic) sensor.stop();
    this.generic = [];
  }

  // ------------------------------------------------------------------ DeviceMotion / DeviceOrientation
  // Resolves once the accelerometer's first sample is kept, or after SILENT_MS without one.
  startEvents() {
    this.mode = "events";
    const s = this.streams;
    let up = null; // the phone's up from the latest orientation, to settle the accelerometer's sign
    let sign = 0; // +1: Android's convention (at rest, up reads +g); -1: the opposite, as some browsers report
    let votes = 0;
    let absolute = false;
    this.onState("accelerometer", "waiting");
    this.onState("gyroscope", "waiting");
    this.onState("orientation", "waiting");
    this.onState("magnetometer", "missing");
    const seen = new Set();
    let started;
    const first = new Promise((resolve) => { started = resolve; });
    const ok = (name) => {
      if (seen.has(name)) return;
      seen.add(name);
      this.onState(name, "ok");
      if (name === "accelerometer") started();
    };
    const motion = (ev) => {
      const a = ev.accelerationIncludingGravity;
      const t = epochMs(ev.timeStamp);
      if (a && a.x !== null) {
        if (sign === 0) {
          // vote over the first samples: gravity along up (or along +z for a phone held flat) is Android's sign
          const along = up ? a.x * up[0] + a.y * up[1] + a.z * up[2] : a.z;
          votes += Math.sign(along);
          if (Math.abs(votes) >= 10) sign = Math.sign(votes);
        }
        if (sign !== 0) {
          s.accelerometer.push(t, [sign * a.x, sign * a.y, sign * a.z], 3);
          ok("accelerometer");
        }
      }
      const r = ev.rotationRate;
      if (r && r.alpha !== null) {
        // rotationRate in degrees a second about the phone's x (alpha), y (beta) and z (gamma) axes, as the
        // specification now says and Chromium reports (older documents had alpha about z)
        s.gyroscope.push(t, [r.alpha * DEG, r.beta * DEG, r.gamma * DEG], 4);
        ok("gyroscope");
      }
    };
    const orientation = (ev) => {
      if (ev.beta === null || ev.gamma === null) return;
      up = upInDevice(ev.beta, ev.gamma);
      let alpha = ev.alpha;
      let isAbsolute = ev.absolute === true || ev.type === "deviceorientationabsolute";
      if (!isAbsolute && typeof ev.webkitCompassHeading === "number" && ev.webkitCompassHeading >= 0) {
        alpha = 360 - ev.webkitCompassHeading; // iOS: the compass heading is clockwise from north
        isAbsolute = true;
      }
      if (alpha === null) return;
      if (isAbsolute) absolute = true;
      else if (absolute) return; // the relative events beside absolute ones add nothing
      const q = quaternionFromEuler(alpha, ev.beta, ev.gamma);
      (isAbsolute ? s.rotation_vector : s.game_rotation_vector).push(epochMs(ev.timeStamp), q, 5);
      ok("orientation");
    };
    const listen = (type, fn) => {
      window.addEventListener(type, fn);
      this.listeners.push([window, type, fn]);
    };
    listen("devicemotion", motion);
    if ("ondeviceorientationabsolute" in window) listen("deviceorientationabsolute", orientation);
    listen("deviceorientation", orientation);
    this.timer = setTimeout(() => {
      for (const name of ["accelerometer", "gyroscope", "orientation"]) {
        if (!seen.has(name)) this.onState(name, this.refused ? "refused" : "missing");
      }
      started();
    }, SILENT_MS);
    return first;
  }
}
