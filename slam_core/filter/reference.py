"""Textbook DynamicSLAM in plain NumPy: one Python object per particle, 2x2 matrices, written for clarity.

It is the oracle of the compiled kernels (it draws the same counter-based random numbers in the same
order, so results agree to rounding) and the baseline of ``bench/engine.py``'s ``reference_ratio``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.filter.floor_plan import PlanIndex
from slam_core.filter.params import FilterParams
from slam_core.filter.state import FilterState

_MASK = (1 << 64) - 1


def _splitmix64(x: int) -> int:
    z = (x + 0x9E3779B97F4A7C15) & _MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
    return z ^ (z >> 31)


class CounterRng:
    """The same stream as ``slam_core.filter.kernels.rng`` for one user."""

    def __init__(self, key: int, counter: int = 0) -> None:
        self.key = int(key)
        self.counter = int(counter)

    def uniform(self) -> float:
        bits = _splitmix64(_splitmix64(self.counter) ^ self.key)
        self.counter += 1
        return ((bits >> 11) + 0.5) / 9007199254740992.0

    def normal(self) -> float:
        return inverse_normal_cdf(self.uniform())


def inverse_normal_cdf(p: float) -> float:
    """Acklam's approximation, term for term as in the kernel."""
    a = (-3.969683028665376e01, 2.209460984245205e02, -2.759285104469687e02, 1.383577518672690e02,
         -3.066479806614716e01, 2.506628277459239e00)  # fmt: skip
    b = (-5.447609879822406e01, 1.615858368580409e02, -1.556989798598866e02, 6.680131188771972e01,
         -1.328068155288572e01)  # fmt: skip
    c = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e00, -2.549732539343734e00,
         4.374664141464968e00, 2.938163982698783e00)  # fmt: skip
    d = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00, 3.754408661907416e00)
    if p < 0.02425 or p > 1.0 - 0.02425:
        q = math.sqrt(-2.0 * math.log(p if p < 0.5 else 1.0 - p))
        x = (((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5]) / (
            (((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0
        )
        return x if p < 0.5 else -x
    q = p - 0.5
    r = q * q
    return (
        (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5])
        * q
        / (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0)
    )


def wrap(a: float) -> float:
    while a >= math.pi:
        a -= 2.0 * math.pi
    while a < -math.pi:
        a += 2.0 * math.pi
    return a


@dataclass
class Anchor:
    mu: np.ndarray
    cov: np.ndarray
    type: int
    count: int = 1
    known: bool = False
    crowd_id: int = -1


@dataclass
class Particle:
    x: float
    y: float
    heading: float
    bias: float
    scale: float
    walk: float
    logw: float
    anchors: list[Anchor] = field(default_factory=list)

    @property
    def s(self) -> np.ndarray:
        return np.array([self.x, self.y])


@dataclass
class ReferenceUser:
    particles: list[Particle]
    rng: CounterRng
    ctrl_cov: np.ndarray  # P_t
    last_obs_heading: float = math.nan
    overflow: int = 0


def _normalise(user: ReferenceUser) -> None:
    logs = np.array([p.logw for p in user.particles])
    top = logs.max()
    total = top + math.log(np.exp(logs - top).sum())
    for p in user.particles:
        p.logw -= total


def crosses_any_wall(walls: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> bool:
    """Whether the step properly crosses any of ``walls`` (S, 4), testing every wall (no index)."""
    ax, ay, bx, by = walls.T

    def orientation(
        px: np.ndarray | float, py: np.ndarray | float, qx: np.ndarray | float, qy: np.ndarray | float,
        rx: np.ndarray | float, ry: np.ndarray | float,
    ) -> np.ndarray:  # fmt: skip
        return np.asarray((qx - px) * (ry - py) - (qy - py) * (rx - px))

    d1, d2 = orientation(ax, ay, bx, by, x0, y0), orientation(ax, ay, bx, by, x1, y1)
    d3, d4 = orientation(x0, y0, x1, y1, ax, ay), orientation(x0, y0, x1, y1, bx, by)
    return bool(np.any((d1 * d2 < 0) & (d3 * d4 < 0)))


def motion(
    user: ReferenceUser,
    length: float,
    obs_heading: float,
    params: FilterParams,
    plan: PlanIndex | None = None,
) -> None:
    mp = params.motion
    log_crossing, log_outside = params.floor_plan.log_weights
    d_obs = 0.0 if math.isnan(user.last_obs_heading) else wrap(obs_heading - user.last_obs_heading)
    for p in user.particles:
        n_len = user.rng.normal()
        n_h = user.rng.normal()
        if mp.model == "paper":
            step = length + mp.step_length_sigma_m * n_len  # Eq. 5
            h = p.heading + d_obs + mp.heading_change_sigma_rad * n_h  # Eq. 6
        else:
            p.walk += mp.heading_walk_sigma_rad * n_h
            step = p.scale * length + mp.step_length_sigma_m * n_len
            h = obs_heading + p.bias + p.walk
        p.heading = wrap(h)
        x0, y0 = p.x, p.y
        p.x += step * math.cos(p.heading)  # Eq. 7
        p.y += step * math.sin(p.heading)  # Eq. 8
        if plan is not None:
            if crosses_any_wall(plan.walls, x0, y0, p.x, p.y):
                p.logw += log_crossing
            if not plan.walkable(np.array([[p.x, p.y]]))[0]:
                p.logw += log_outside
    if plan is not None:
        _normalise(user)
    user.last_obs_heading = obs_heading
    rot = np.array(
        [[math.cos(obs_heading), -math.sin(obs_heading)], [math.sin(obs_heading), math.cos(obs_heading)]]
    )
    step_cov = rot @ np.diag([mp.step_length_sigma_m**2, (length * mp.heading_change_sigma_rad) ** 2]) @ rot.T
    cap = params.human.control_covariance_cap_m2
    c = user.ctrl_cov + step_cov
    c[0, 0] = min(c[0, 0], cap)
    c[1, 1] = min(c[1, 1], cap)
    lim = 0.999 * math.sqrt(c[0, 0] * c[1, 1])
    c[0, 1] = c[1, 0] = max(-lim, min(lim, c[0, 1]))
    user.ctrl_cov = c


def _control_cov(user: ReferenceUser) -> np.ndarray:
    return user.ctrl_cov + 1e-4 * np.eye(2)


def _sample(rng_n1: float, rng_n2: float, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    a, b, c = cov[0, 0], cov[0, 1], cov[1, 1]
    l11 = math.sqrt(max(a, 0.0))
    l21 = b / l11 if l11 > 0 else 0.0
    l22 = math.sqrt(max(c - l21 * l21, 0.0))
    return np.array([mean[0] + l11 * rng_n1, mean[1] + l21 * rng_n1 + l22 * rng_n2])


def _log_gauss(v: np.ndarray, cov: np.ndarray) -> float:
    return float(
        -math.log(2 * math.pi) - 0.5 * math.log(np.linalg.det(cov)) - 0.5 * v @ np.linalg.solve(cov, v)
    )


def building_anchor(user: ReferenceUser, detected: int, params: FilterParams) -> None:
    ap = params.anchors
    posterior = ap.type_posterior
    R = ap.detection_sigma_m**2 * np.eye(2)
    P = _control_cov(user)
    for p in user.particles:
        s = p.s
        best, best_log = (
            -1,
            math.log(ap.new_anchor_likelihood) + math.log(posterior[detected, detected]),
        )  # Eq. 16
        for n, anchor in enumerate(p.anchors):
            type_p = posterior[anchor.type, detected]
            if type_p <= 0:
                continue
            lp = _log_gauss(s - anchor.mu, anchor.cov + R + P) + math.log(type_p)  # Eq. 15
            if lp > best_log:
                best, best_log = n, lp
        n1, n2 = user.rng.normal(), user.rng.normal()
        if best < 0:
            if len(p.anchors) < ap.capacity:
                p.anchors.append(Anchor(mu=s.copy(), cov=R.copy(), type=detected))  # Algorithm 3 lines 2-3
            else:
                user.overflow += 1
        else:
            anchor = p.anchors[best]
            Q = anchor.cov + R
            sigma = np.linalg.inv(np.linalg.inv(Q) + np.linalg.inv(P))  # Algorithm 1 line 3, J_s = -I
            mean = s + sigma @ np.linalg.solve(Q, anchor.mu - s)  # line 5
            new_s = _sample(n1, n2, mean, sigma)  # line 7
            p.x, p.y = float(new_s[0]), float(new_s[1])
            if not anchor.known:
                K = anchor.cov @ np.linalg.inv(Q)  # Algorithm 3 line 5
                anchor.mu = anchor.mu + K @ (new_s - anchor.mu)  # line 6
                anchor.cov = (np.eye(2) - K) @ anchor.cov  # line 7
            anchor.count += 1
        p.logw += best_log  # Eq. 17
    _normalise(user)
    user.ctrl_cov = np.zeros((2, 2))


def human_anchor(
    user: ReferenceUser, peer_mean: np.ndarray, peer_cov: np.ndarray, z: float, r: float, params: FilterParams
) -> None:
    hp = params.human
    P = _control_cov(user)
    eps = hp.outlier_probability
    for p in user.particles:
        s = p.s
        h, J = _range(s, peer_mean)
        Q = float(J @ peer_cov @ J) + r  # Eq. 12
        S = float(J @ P @ J) + Q
        lik = (1 - eps) * math.exp(-0.5 * (z - h) ** 2 / S) / math.sqrt(
            2 * math.pi * S
        ) + eps / hp.max_range_m
        p.logw += math.log(lik)
        mu = s.copy()
        sigma = P
        for _ in range(hp.max_iterations):
            h_mu, J = _range(mu, peer_mean)
            Q = float(J @ peer_cov @ J) + r
            sigma = np.linalg.inv(np.outer(J, J) / Q + np.linalg.inv(P))  # Eq. 11
            K = sigma @ J / Q  # Eq. 13
            new_mu = s + K * (z - h_mu - J @ (s - mu))  # Eq. 10 (iterated)
            moved = float(np.linalg.norm(new_mu - mu))
            mu = new_mu
            if hp.sampling != "iterative" or moved < hp.beta_m:
                break
        new_s = _sample(user.rng.normal(), user.rng.normal(), mu, sigma)  # Eq. 14
        p.x, p.y = float(new_s[0]), float(new_s[1])
    _normalise(user)
    user.ctrl_cov = np.zeros((2, 2))


def _range(s: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
    d = s - b
    h = float(np.linalg.norm(d))
    if h < 1e-9:
        return 0.0, np.array([1.0, 0.0])
    return h, d / h


def ancestors(weights: np.ndarray, scheme: str, rng: CounterRng) -> np.ndarray:
    n = len(weights)
    cdf = np.cumsum(weights)

    def inverse(us: np.ndarray, w_cdf: np.ndarray) -> list[int]:
        out = []
        for u in us:
            j = 0
            while u >= w_cdf[j] and j < len(w_cdf) - 1:
                j += 1
            out.append(j)
        return out

    if scheme == "systematic":
        u0 = rng.uniform()
        return np.array(inverse((np.arange(n) + u0) / n, cdf))
    if scheme == "stratified":
        return np.array(inverse(np.array([(k + rng.uniform()) / n for k in range(n)]), cdf))
    if scheme == "multinomial":
        return np.array(inverse(np.sort([rng.uniform() for _ in range(n)]), cdf))
    copies = np.floor(n * weights).astype(int)
    out = [j for j in range(n) for _ in range(copies[j])]
    rest = n - len(out)
    if rest:
        residual = n * weights - copies
        residual /= residual.sum()
        out += inverse(np.sort([rng.uniform() for _ in range(rest)]), np.cumsum(residual))
    return np.array(out)


def resample(user: ReferenceUser, params: FilterParams) -> bool:
    rp = params.resampling
    w = np.exp([p.logw for p in user.particles])
    w = w / w.sum()
    n = len(w)
    if (
        rp.ess_threshold < 1.0
        and 1.0 / np.sum(np.exp(2 * np.array([p.logw for p in user.particles]))) >= rp.ess_threshold * n
    ):
        return False
    idx = ancestors(w, rp.scheme, user.rng)
    old = user.particles
    user.particles = [
        Particle(
            old[j].x,
            old[j].y,
            old[j].heading,
            old[j].bias,
            old[j].scale,
            old[j].walk,
            -math.log(n),
            [Anchor(a.mu.copy(), a.cov.copy(), a.type, a.count, a.known, a.crowd_id) for a in old[j].anchors],
        )
        for j in idx
    ]
    if params.motion.model == "bias-scale" and (rp.roughening_bias_rad > 0 or rp.roughening_scale > 0):
        for p in user.particles:  # roughening (Gordon et al. 1993)
            p.bias += rp.roughening_bias_rad * user.rng.normal()
            p.scale = max(0.2, p.scale + rp.roughening_scale * user.rng.normal())
    return True


def summary(user: ReferenceUser) -> np.ndarray:
    w = np.exp([p.logw for p in user.particles])
    pts = np.array([[p.x, p.y] for p in user.particles])
    mean = w @ pts
    d = pts - mean
    cov = (w[:, None] * d).T @ d
    best = int(np.argmax([p.logw for p in user.particles]))
    heading = math.atan2(
        sum(wi * math.sin(p.heading) for wi, p in zip(w, user.particles, strict=True)),
        sum(wi * math.cos(p.heading) for wi, p in zip(w, user.particles, strict=True)),
    )
    return np.array(
        [mean[0], mean[1], cov[0, 0] + 1e-6, cov[0, 1], cov[1, 1] + 1e-6, pts[best, 0], pts[best, 1], heading]
    )


def from_state(s: FilterState, u: int) -> ReferenceUser:
    """User slot ``u`` of the engine's arrays as textbook objects (same random stream position)."""
    particles = []
    for m in range(s.n_particles):
        anchors = [
            Anchor(
                mu=s.map_mu[u, m, k].copy(),
                cov=np.array(
                    [
                        [s.map_cov[u, m, k, 0], s.map_cov[u, m, k, 1]],
                        [s.map_cov[u, m, k, 1], s.map_cov[u, m, k, 2]],
                    ]
                ),
                type=int(s.map_type[u, m, k]),
                count=int(s.map_count[u, m, k]),
                known=bool(s.map_known[u, m, k]),
                crowd_id=int(s.map_crowd_id[u, m, k]),
            )
            for k in range(s.map_n[u, m])
        ]
        particles.append(
            Particle(
                float(s.x[u, m]),
                float(s.y[u, m]),
                float(s.heading[u, m]),
                float(s.bias[u, m]),
                float(s.scale[u, m]),
                float(s.walk[u, m]),
                float(s.logw[u, m]),
                anchors,
            )
        )
    c = s.ctrl_cov[u]
    return ReferenceUser(
        particles=particles,
        rng=CounterRng(int(s.rng_key[u]), int(s.rng_ctr[u])),
        ctrl_cov=np.array([[c[0], c[1]], [c[1], c[2]]]),
        last_obs_heading=float(s.last_obs_heading[u]),
    )
