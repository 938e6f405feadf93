"""Joint least-squares estimate of the crowd's anchor map.

Fusing each user's filtered position at a detection (``CrowdMapBuilder``) lets errors spread: users
corrected by a misplaced anchor contribute that error again, and on hard testbed seeds anchors with 7-15
contributors stayed 1.5-2.5 m off. Here every detection so far is explained jointly: user u's position at
detection i is F_u + s_u R(b_u) D_ui, with F_u its start fix, D_ui the dead-reckoned displacement (observed
step lengths along observed headings), b_u its heading bias and s_u its step scale, both unknown with the
filter's priors. Residuals tie consecutive detections of a user to the difference of their anchors
(sigma grows with the distance walked between them), the first detection to the start fix, and known
anchors stay fixed. A soft-L1 loss limits wrong associations. The solution (anchor means, and covariances
from the Gauss-Newton information) replaces the sequential fusion as the shared map.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares


@dataclass
class _UserTrack:
    start: np.ndarray
    anchor: list[int] = field(default_factory=list)
    displacement: list[np.ndarray] = field(default_factory=list)
    walked: list[float] = field(default_factory=list)
    sigma: list[float] = field(default_factory=list)  # each detection's own sigma (m)


@dataclass(frozen=True)
class CrowdGraphParams:
    start_sigma_m: float = 0.5
    detection_sigma_m: float = 0.5
    drift_fraction: float = 0.03
    """Standard deviation of dead reckoning left after bias and scale, as a fraction of the distance."""
    bias_sigma_rad: float = np.radians(10.0)
    scale_sigma: float = 0.12
    loss_scale: float = 2.0


@dataclass(frozen=True)
class GraphProblem:
    anchors: list[int]
    users: list[int]
    residuals: Callable[[np.ndarray], np.ndarray]
    jacobian: Callable[[np.ndarray], sparse.csr_matrix]
    x0: np.ndarray


class CrowdGraph:
    def __init__(self, params: CrowdGraphParams | None = None) -> None:
        self.params = params or CrowdGraphParams()
        self._users: dict[int, _UserTrack] = {}
        self._known: dict[int, np.ndarray] = {}
        # the last solution's heading bias and step scale per user: warm starts of the next solve
        self._bias: dict[int, float] = {}
        self._scale: dict[int, float] = {}

    def set_known(self, anchor: int, position: np.ndarray) -> None:
        self._known[anchor] = np.asarray(position, dtype=float).copy()

    def add_user(self, user: int, start: np.ndarray) -> None:
        self._users[user] = _UserTrack(np.asarray(start, dtype=float).copy())

    def relabel(self, old: int, new: int) -> None:
        """Detections of anchor ``old`` now refer to ``new`` (two crowd anchors merged)."""
        for track in self._users.values():
            track.anchor = [new if a == old else a for a in track.anchor]

    def forget_user(self, user: int) -> None:
        """Drop a user's track (bounded memory on a long-running server); anchors keep their estimates."""
        self._users.pop(user, None)
        self._bias.pop(user, None)
        self._scale.pop(user, None)

    @property
    def n_users(self) -> int:
        return len(self._users)

    def add_detection(
        self, user: int, anchor: int, displacement: np.ndarray, walked_m: float, sigma_m: float | None = None
    ) -> None:
        """``sigma_m``: how far from the anchor the detection may be (default ``detection_sigma_m``; a radio
        signature's range is metres, a stair's is an arm's length)."""
        track = self._users[user]
        track.sigma.append(self.params.detection_sigma_m if sigma_m is None else float(sigma_m))
        track.anchor.append(int(anchor))
        track.displacement.append(np.asarray(displacement, dtype=float).copy())
        track.walked.append(float(walked_m))

    def solve(
        self, initial: dict[int, np.ndarray], touching: set[int] | None = None
    ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """Anchor means and 2x2 covariances for every unknown anchor seen (or only those in the connected
        parts of the graph that hold an anchor of ``touching``); ``initial`` seeds the means. Each connected
        part (users and the unknown anchors they detected: a floor's crowd, or a quarter no one walked from
        another) is solved on its own: the parts share no variable, so their optima are the joint one's, and
        a floor's solve neither waits for nor moves the others' anchors."""
        means: dict[int, np.ndarray] = {}
        covs: dict[int, np.ndarray] = {}
        for users in self.components():
            if touching is not None and not any(
                a in touching and a not in self._known for u in users for a in self._users[u].anchor
            ):
                continue
            problem = self.problem(initial, users)
            if problem is not None:
                part_means, part_covs = self._solved(problem)
                means.update(part_means)
                covs.update(part_covs)
        return means, covs

    def components(self) -> list[list[int]]:
        """The users with unknown anchors, grouped by the connected parts of the graph (two users are in one
        when a chain of their detections' unknown anchors joins them; known anchors are fixed and join
        nothing), each in the order users were added, the parts by their first user."""
        parent: dict[int, int] = {}

        def root(a: int) -> int:
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            return a

        first: dict[int, int] = {}  # a user's first unknown anchor
        for u, t in self._users.items():
            unknown = [a for a in t.anchor if a not in self._known]
            if not unknown:
                continue
            for a in unknown:
                parent.setdefault(a, a)
            r = root(unknown[0])
            for a in unknown[1:]:
                other = root(a)
                if other != r:
                    parent[other] = r
            first[u] = unknown[0]
        parts: dict[int, list[int]] = {}
        for u, a in first.items():
            parts.setdefault(root(a), []).append(u)
        return list(parts.values())

    def _solved(self, problem: GraphProblem) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        result = least_squares(
            problem.residuals,
            problem.x0,
            jac=problem.jacobian,
            loss="soft_l1",
            f_scale=self.params.loss_scale,
            x_scale="jac",
            max_nfev=100,
        )
        x = result.x
        n_a, n_u = len(problem.anchors), len(problem.users)
        for k, u in enumerate(problem.users):
            self._bias[u] = float(x[2 * n_a + k])
            self._scale[u] = float(x[2 * n_a + n_u + k])
        jac = problem.jacobian(x)
        cov = np.linalg.inv((jac.T @ jac).toarray() + 1e-9 * np.eye(x.size))
        means, covs = {}, {}
        for j, a in enumerate(problem.anchors):
            means[a] = x[2 * j : 2 * j + 2].copy()
            block = cov[2 * j : 2 * j + 2, 2 * j : 2 * j + 2]
            covs[a] = 0.5 * (block + block.T) + 1e-4 * np.eye(2)
        return means, covs

    def problem(self, initial: dict[int, np.ndarray], among: list[int] | None = None) -> GraphProblem | None:
        """The weighted residuals, their analytic Jacobian and the starting point over the variables
        (unknown anchors' x, y; each user's bias; each user's scale) of the users ``among`` (all by default)
        and the anchors they detected, or None when nothing is to solve."""
        p = self.params
        tracks = self._users if among is None else {u: self._users[u] for u in among}
        anchors = sorted({a for t in tracks.values() for a in t.anchor if a not in self._known})
        users = [u for u, t in tracks.items() if t.anchor]
        if not anchors or not users:
            return None
        a_index = {a: i for i, a in enumerate(anchors)}
        n_a, n_u = len(anchors), len(users)
        # one row per detection: this anchor, the previous anchor (or the start fix), the displacement
        # walked between them and the residual's standard deviation
        cur, prev, fixed_cur, fixed_prev, delta, sigma, user_of = [], [], [], [], [], [], []
        for k, u in enumerate(users):
            t = self._users[u]
            for i, a in enumerate(t.anchor):
                if i == 0:
                    d, var, pa, fp = (
                        t.displacement[0],
                        p.start_sigma_m**2 + t.sigma[0] ** 2,
                        -1,
                        t.start,
                    )
                    var += (p.drift_fraction * t.walked[0]) ** 2
                else:
                    d = t.displacement[i] - t.displacement[i - 1]
                    var = (
                        t.sigma[i] ** 2
                        + t.sigma[i - 1] ** 2
                        + (p.drift_fraction * (t.walked[i] - t.walked[i - 1])) ** 2
                    )
                    b = t.anchor[i - 1]
                    pa = a_index.get(b, -1)
                    fp = self._known.get(b, np.zeros(2))
                cur.append(a_index.get(a, -1))
                fixed_cur.append(self._known.get(a, np.zeros(2)))
                prev.append(pa)
                fixed_prev.append(fp)
                delta.append(d)
                sigma.append(np.sqrt(var))
                user_of.append(k)
        cur_i, prev_i, k_i = np.array(cur), np.array(prev), np.array(user_of)
        fixed_c, fixed_p, d_all = np.array(fixed_cur), np.array(fixed_prev), np.array(delta)
        w = 1.0 / np.array(sigma)
        n_rows = cur_i.size
        n_var = 2 * n_a + 2 * n_u
        x0 = np.concatenate(
            [
                np.concatenate([initial.get(a, np.zeros(2)) for a in anchors]),
                np.array([self._bias.get(u, 0.0) for u in users]),
                np.array([self._scale.get(u, 1.0) for u in users]),
            ]
        )

        def positions(x: np.ndarray, index: np.ndarray, fixed: np.ndarray) -> np.ndarray:
            a = x[: 2 * n_a].reshape(n_a, 2)
            return np.where((index >= 0)[:, None], a[np.clip(index, 0, max(n_a - 1, 0))], fixed)

        def rotated(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            b = x[2 * n_a : 2 * n_a + n_u][k_i]
            s = x[2 * n_a + n_u :][k_i]
            c, sn = np.cos(b), np.sin(b)
            rd = np.column_stack([c * d_all[:, 0] - sn * d_all[:, 1], sn * d_all[:, 0] + c * d_all[:, 1]])
            return (
                rd,
                s,
                np.column_stack([-sn * d_all[:, 0] - c * d_all[:, 1], c * d_all[:, 0] - sn * d_all[:, 1]]),
            )

        def residuals(x: np.ndarray) -> np.ndarray:
            rd, s, _ = rotated(x)
            r = (positions(x, cur_i, fixed_c) - positions(x, prev_i, fixed_p) - s[:, None] * rd) * w[:, None]
            priors = np.concatenate(
                [x[2 * n_a : 2 * n_a + n_u] / p.bias_sigma_rad, (x[2 * n_a + n_u :] - 1.0) / p.scale_sigma]
            )
            return np.concatenate([r.ravel(), priors])

        def jacobian(x: np.ndarray) -> sparse.csr_matrix:
            """Sparse: each detection row touches two anchors and one user's bias and scale (a dense
            Jacobian made the joint solve dominate a crowd replay once hundreds of anchors exist)."""
            rd, s, drd = rotated(x)
            rows_out, cols_out, vals_out = [], [], []
            rows = np.arange(n_rows)
            has_cur, has_prev = cur_i >= 0, prev_i >= 0
            for axis in (0, 1):
                r_idx = 2 * rows + axis
                rows_out += [r_idx[has_cur], r_idx[has_prev], r_idx, r_idx]
                cols_out += [
                    2 * cur_i[has_cur] + axis,
                    2 * prev_i[has_prev] + axis,
                    2 * n_a + k_i,
                    2 * n_a + n_u + k_i,
                ]
                vals_out += [w[has_cur], -w[has_prev], -s * drd[:, axis] * w, -rd[:, axis] * w]
            prior_rows = 2 * n_rows + np.arange(2 * n_u)
            rows_out.append(prior_rows)
            cols_out.append(2 * n_a + np.arange(2 * n_u))
            vals_out.append(np.r_[np.full(n_u, 1.0 / p.bias_sigma_rad), np.full(n_u, 1.0 / p.scale_sigma)])
            return sparse.csr_matrix(
                (np.concatenate(vals_out), (np.concatenate(rows_out), np.concatenate(cols_out))),
                shape=(2 * n_rows + 2 * n_u, n_var),
            )

        return GraphProblem(anchors, users, residuals, jacobian, x0)
