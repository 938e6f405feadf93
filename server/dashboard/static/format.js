// How the page writes a time: UTC to the second, the same everywhere (phones' clocks, not this browser's zone).

// The floor an estimate says, and how sure the filter is of it (estimates stored before floors have no share).
export function fmtFloor(est) {
  const p = est.floor_probability;
  if (p === undefined || p === null || p >= 0.995) return String(est.floor);
  return `${est.floor} (${Math.round(100 * p)} % sure${p < 0.9 ? ": between floors" : ""})`;
}

export function fmtTime(ms) {
  return ms ? new Date(ms).toISOString().replace("T", " ").slice(0, 19) + " UTC" : "never";
}
