// The public REST API, with the key in the Authorization header (never in a URL). A refusal becomes a
// ProblemError carrying the server's RFC 9457 problem, so the page can show what was wrong.

export class ProblemError extends Error {
  constructor(status, problem) {
    const title = problem.title || `HTTP ${status}`;
    super(problem.detail ? `${title}: ${problem.detail}` : title);
    this.status = status;
    this.problem = problem;
  }

  // One line per offending field, after the summary.
  describe() {
    const fields = (this.problem.errors || []).map((e) => `${e.loc}: ${e.msg}`);
    return [this.message, ...fields].join("\n");
  }
}

export class Api {
  constructor(key, onUnauthorized) {
    this.key = key;
    this.onUnauthorized = onUnauthorized;
  }

  async request(method, path, body = undefined, { blob = false } = {}) {
    const headers = { Authorization: `Bearer ${this.key}`, Accept: "application/json" };
    const init = { method, headers, cache: "no-store" };
    if (body !== undefined) {
      headers["Content-Type"] = "application/json";
      init.body = typeof body === "string" ? body : JSON.stringify(body);
    }
    let response;
    try {
      response = await fetch(path, init);
    } catch (err) {
      throw new ProblemError(0, { title: "Server unreachable", detail: String(err.message || err) });
    }
    if (!response.ok) {
      let problem;
      try {
        problem = await response.json();
      } catch {
        problem = { title: response.statusText || "Request failed" };
      }
      const error = new ProblemError(response.status, problem);
      if (response.status === 401 && this.onUnauthorized) this.onUnauthorized(error);
      throw error;
    }
    if (response.status === 204) return null;
    return blob ? response.blob() : response.json();
  }

  get(path) { return this.request("GET", path); }
  put(path, body) { return this.request("PUT", path, body); }
  post(path, body) { return this.request("POST", path, body); }
  del(path) { return this.request("DELETE", path); }
}
