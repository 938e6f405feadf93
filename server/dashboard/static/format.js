// How the page writes a time: UTC to the second, the same everywhere (phones' clocks, not this browser's zone).

export function fmtTime(ms) {
  return ms ? new Date(ms).toISOString().replace("T", " ").slice(0, 19) + " UTC" : "never";
}
