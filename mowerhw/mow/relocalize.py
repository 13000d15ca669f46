"""Global relocalization: the mower's pose from one frame, with no prior (issue 18).

For a mower switched on in the middle of the lawn, or carried there. Measured first (pixel
level, paper scenario): recognising landmarks by their ORB descriptors does not work on a
lawn's landmarks — the board corners look alike, and a board seen from its other side gives
nearly the inverted descriptor, so only 2–5 of ~100 descriptor candidates per frame were right
(RANSAC over them: 11 answers in 542 frames, 7 of them wrong). What does tell places apart is
the *geometry*: where, around the mower and how high, the landmarks appear. So:

1. **Search** — a grid of positions over the map's areas (every :attr:`grid_m`) at the dock's
   camera height, the mower upright. At each position a landmark's elevation does not depend
   on the heading, its azimuth shifts with it: every (observed bearing, landmark) pair whose
   elevations agree within :attr:`elevation_tol_rad` votes for a heading (landmark azimuth −
   observed azimuth), and the votes of all pairs of all positions are counted in heading bins
   at once (numpy, no loop per landmark).
2. **Refine** — the best distinct (position, heading) hypotheses are refined: observed bearings
   associated with the nearest predicted landmark (a tightening angle), (x, y, heading) fitted
   to them (robust least squares over the angular residuals; three unknowns, not six: a free
   tilt and height let a wrong place explain many bearings by chance), inliers counted at
   :attr:`inlier_angle_rad`.
3. **Polish** — a refinement can stop in a local optimum a few decimetres off, where the true
   pose explains the bearings far better at sub-degree precision: every pose of a 5 cm / 1°
   grid around the best is scored at once (soft score, σ 1°), its best ten poses and best
   five other local maxima are refined by annealing the score's kernel from 1° down to the
   frame's own bearing σ (at least 0.1°), and the one with the best sharp soft score at that
   σ is kept (:meth:`GlobalRelocalizer._polish`):
   a board's corners are a lattice, and a pose that pairs the bearings with their corners'
   neighbours explains as many of them, only less sharply. Its ~120 weighted fits a frame are
   Gauss–Newton with the residual's closed-form Jacobian
   (:meth:`GlobalRelocalizer._residual_jacobian`), not a general solver's numerical one.
4. **Unique or nothing** — an answer only with at least :attr:`min_inliers` inliers spread
   around the mower, if no place more than 1 m or 15° away has :attr:`ambiguity_ratio` of its
   inliers unless it has :attr:`ambiguity_margin` fewer (a look-alike place: in a symmetric
   garden the twin place explains every look-alike landmark, and only the others tell the
   two apart), and no refined optimum more than 0.15 m away or turned more than 1° scores
   90 % as well (not pinned down: a board's corners are a lattice, and a turn by one step of
   it pairs each bearing with its landmark's neighbour). Otherwise no answer, with the reason.
5. **The answer's fit** — (x, y, heading) fitted once more to the inliers, each weighed by
   Huber at the residuals' robust σ (a feature beside a landmark's corner, up to the 1°
   inlier angle off, no longer weighs as much as a true one), with its covariance from the
   same weights (:meth:`GlobalRelocalizer._final_fit`, :meth:`GlobalRelocalizer.covariance`).

With a compass (``locate(bearings, heading=(ψ, σ))``: the magnetometer's heading in the map's
frame, :mod:`mowerhw.estimation.compass`) the search keeps only the headings within
:meth:`GlobalRelocalizer.compass_tolerance` of it — votes, the answer and its rivals alike —
so a look-alike place turned far from it is no rival; the geometry still has to pin the pose
down by itself.

With a prior (``locate(bearings, near=(x, y, heading))``: the dock, a resumed pose, the pose
before a lock-out) the refinement starts at the prior, and the answer is the best optimum
near it — but the grid vote still runs, for rivals: a prior that is wrong (a mower carried
while switched off, put down where the dock pose says nothing) can still refine to a chance
fit of a few bearings near it (measured on the bench: 8 inliers 1.2 m and 111° off, where
the whole-map search found the true pose with 34), so the prior's answer stands only if no
place elsewhere explains clearly more bearings (:meth:`GlobalRelocalizer._beaten`): a
look-alike twin that explains about as many does not overrule it — telling twins apart is
what the prior is for. Nor may a pose beside the answer, more than 0.15 m or 1° from it,
explain clearly more: the answer is then a local optimum the refinement and the polish did
not leave (replayed on a bench map's rendered view, this rule alone refused the two wrong
answers of 800 priors). An optimum answers for the prior only within 1 m and 15° of it
(:meth:`GlobalRelocalizer._near`), whatever start it was refined from; when none there
explains enough bearings, the prior says nothing and the frame is judged as a search of the
whole map (its ambiguity rule), not refused until the search widens. Whether to *trust* an
answer (the same pose from more than one frame, through the odometry) is the caller's:
:class:`mowerhw.mow.recovery.RelocalizationSearch`.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import shapely
from numpy.typing import NDArray
from scipy.ndimage import maximum_filter
from scipy.optimize import least_squares
from scipy.stats import chi2

from mowerhw.common.geometry import cross_rows, wrap_angle, yaw_rotation
from mowerhw.common.relocalization import Relocalization
from mowerhw.map import LawnMap

FloatArray = NDArray[np.float64]

MIN_AZIMUTH_SPREAD_RAD = math.radians(90.0)
DISTINCT_M = 1.0
DISTINCT_RAD = math.radians(15.0)
#: the compass's tolerance: 3 σ, at least this (its σ is the taught spread and the
#: reading's; a motor or a steel post nearby bends the field more than they say) …
COMPASS_MIN_TOLERANCE_RAD = math.radians(30.0)
#: … and a compass less sure than this is not used at all
COMPASS_MAX_TOLERANCE_RAD = math.radians(60.0)


def _cross_rows_jac(a: FloatArray, db: FloatArray) -> FloatArray:
    """(n, 3, k): a × each column of ``db`` (n, 3, k), row by row — the derivative of
    a × b(x) when ``db`` is b's."""
    out = np.empty_like(db)
    out[:, 0] = a[:, 1, None] * db[:, 2] - a[:, 2, None] * db[:, 1]
    out[:, 1] = a[:, 2, None] * db[:, 0] - a[:, 0, None] * db[:, 2]
    out[:, 2] = a[:, 0, None] * db[:, 1] - a[:, 1, None] * db[:, 0]
    return out


class GlobalRelocalizer:
    """The pose from one frame's bearings and the map's landmarks (module doc)."""

    #: positions per block of the vote (its table: 256 × 90 bins × 2 bytes, in cache)
    VOTE_BLOCK = 256

    def __init__(
        self,
        lawn_map: LawnMap,
        grid_m: float = 0.25,
        yaw_bin_rad: float = math.radians(4.0),
        elevation_tol_rad: float = math.radians(3.0),
        inlier_angle_rad: float = math.radians(1.0),
        min_inliers: int = 8,
        ambiguity_ratio: float = 0.7,
        ambiguity_margin: int = 6,
        max_range_m: float = 30.0,
        hypotheses: int = 8,
    ) -> None:
        self.ids = np.array([lm.id for lm in lawn_map.landmarks], dtype=np.int64)
        self.points = np.array([lm.xyz for lm in lawn_map.landmarks], dtype=np.float64)
        self.points = self.points.reshape(-1, 3)
        # each landmark's position variance (m², the mean of its three axes): how much its
        # bearing may be off whatever the pose (the answer's covariance)
        self._point_cov = np.array(
            [lm.covariance for lm in lawn_map.landmarks], dtype=np.float64
        ).reshape(-1, 3, 3)
        self._point_var = np.trace(self._point_cov, axis1=1, axis2=2) / 3.0
        self.grid_m = grid_m
        self.yaw_bin = yaw_bin_rad
        self.n_bins = math.ceil(2 * math.pi / yaw_bin_rad)
        self.elevation_tol_rad = elevation_tol_rad
        self.inlier_angle_rad = inlier_angle_rad
        self.min_inliers = min_inliers
        self.ambiguity_ratio = ambiguity_ratio
        self.ambiguity_margin = ambiguity_margin
        self.max_range_m = max_range_m
        self.n_hypotheses = hypotheses
        self.height = float(lawn_map.dock_position[2])
        # every area, navigation areas too: the mower may be anywhere in them
        region = shapely.union_all([shapely.Polygon(a.polygon) for a in lawn_map.all_areas()])
        region = region.buffer(0.5)
        minx, miny, maxx, maxy = region.bounds
        gx, gy = np.meshgrid(np.arange(minx, maxx, grid_m), np.arange(miny, maxy, grid_m))
        inside = shapely.contains_xy(region, gx, gy)
        self.grid = np.column_stack([gx[inside], gy[inside]])  # (P, 2)
        # every (position, landmark) pair in range, in blocks of positions, each sorted by
        # elevation: an observation's compatible pairs in a block are one slice (the vote
        # costs what it counts, not P × N), and a block's part of the vote table stays in
        # the processor's cache while its slices are counted. Built a block at a time and
        # only the pairs kept: a garden's (P, N) tables would not fit a mower's memory
        blocks = range(0, self.grid.shape[0], self.VOTE_BLOCK)
        counts = [0] + [  # a first pass counts the pairs, so the build holds no second copy
            int(np.count_nonzero(self.tables(slice(p0, p0 + self.VOTE_BLOCK), True)[2]))
            for p0 in blocks
        ]
        self._block_start = starts = np.cumsum(counts)
        self._pair_elevation = np.empty(starts[-1])
        self._pair_azimuth_bins = np.empty(starts[-1])
        self._pair_vote_base = np.empty(starts[-1], np.intp)
        for a, b, p0 in zip(starts[:-1].tolist(), starts[1:].tolist(), blocks, strict=True):
            azimuth, elevation, in_range = self.tables(slice(p0, p0 + self.VOTE_BLOCK))
            pi, ni = np.nonzero(in_range)  # pi: the position within the block
            pair_elevation = elevation[pi, ni]
            order = np.argsort(pair_elevation)
            self._pair_elevation[a:b] = pair_elevation[order]
            # a pair's azimuth in heading bins, in [0, bins), and its first vote in its block
            self._pair_azimuth_bins[a:b] = (azimuth[pi, ni][order] % (2 * math.pi)) / yaw_bin_rad
            self._pair_vote_base[a:b] = pi[order] * self.n_bins

    def tables(
        self, rows: slice, range_only: bool = False
    ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """From the grid positions ``rows`` to every landmark: azimuth and elevation (rad,
        the mower upright at the dock's camera height), and whether within the search's
        range — (positions, landmarks) each (``range_only``: the last alone, the others
        empty)."""
        d = self.points[None, :, :2] - self.grid[rows, None, :]
        horizontal = np.hypot(d[..., 0], d[..., 1])
        in_range = horizontal <= self.max_range_m
        if range_only:
            return np.zeros((0, 0)), np.zeros((0, 0)), in_range
        azimuth = np.arctan2(d[..., 1], d[..., 0])
        elevation = np.arctan2(self.points[None, :, 2] - self.height, horizontal)
        return azimuth, elevation, in_range

    @property
    def table_bytes(self) -> int:
        """Memory the precomputed search holds: the in-range pairs' three arrays."""
        pairs = (self._pair_elevation, self._pair_azimuth_bins, self._pair_vote_base)
        return sum(a.nbytes for a in pairs)

    # ---------------------------------------------------------------------------- search

    def _votes(self, azimuth: FloatArray, elevation: FloatArray) -> NDArray[np.int64]:
        """(P, bins) count of elevation-compatible (observation, landmark) pairs per heading."""
        p_n, n_bins = self.grid.shape[0], self.n_bins
        # a count never exceeds the observations: the narrowest type that holds them keeps
        # the table in cache (the scattered increments below are most of the cost)
        dtype = np.int16 if azimuth.size < np.iinfo(np.int16).max else np.int64
        votes = np.zeros(p_n * n_bins, dtype=dtype)
        tol = self.elevation_tol_rad
        # the heading, in bins, of (pair azimuth − observed azimuth) + a turn: in (0, 2 bins)
        shift = (azimuth % (2 * math.pi)) / self.yaw_bin - n_bins
        starts = self._block_start.tolist()
        size = max((b - a for a, b in itertools.pairwise(starts)), default=0)  # a block's pairs
        turn, index = np.empty(size), np.empty(size, dtype=np.intp)  # reused buffers
        for blk, (s0, s1) in enumerate(itertools.pairwise(starts)):
            block = votes[blk * self.VOTE_BLOCK * n_bins : (blk + 1) * self.VOTE_BLOCK * n_bins]
            ele = self._pair_elevation[s0:s1]
            lo = (s0 + np.searchsorted(ele, elevation - tol, side="right")).tolist()
            hi = (s0 + np.searchsorted(ele, elevation + tol, side="left")).tolist()
            for k, (a, b) in enumerate(zip(lo, hi, strict=True)):  # an observation's pairs
                if a >= b:
                    continue
                idx = index[: b - a]
                idx[...] = np.subtract(self._pair_azimuth_bins[a:b], shift[k], out=turn[: b - a])
                np.subtract(idx, n_bins, out=idx, where=idx >= n_bins)
                idx += self._pair_vote_base[a:b]
                # one vote per observation per (position, bin): a fancy-indexed += adds
                # once per distinct index, however often it repeats (unlike np.add.at)
                block[idx] += 1
        return votes.reshape(p_n, n_bins).astype(np.int64)

    @staticmethod
    def compass_tolerance(heading: tuple[float, float] | None) -> float | None:
        """How far from the compass's ψ a heading may be (module doc), or None: no compass,
        or one too unsure to use."""
        if heading is None or not (math.isfinite(heading[0]) and math.isfinite(heading[1])):
            return None
        tol = max(COMPASS_MIN_TOLERANCE_RAD, 3.0 * heading[1])
        return tol if tol <= COMPASS_MAX_TOLERANCE_RAD else None

    def _within_compass(self, votes: NDArray[np.int64], psi: float, tol: float) -> None:
        """Zero the votes of the headings farther than ``tol`` (+ a bin) from ``psi``."""
        bin_yaw = (np.arange(self.n_bins, dtype=np.float64) + 1.0) * self.yaw_bin
        off = np.abs(wrap_angle(bin_yaw - psi))
        votes[:, off > tol + self.yaw_bin] = 0

    def _hypotheses(self, votes: NDArray[np.int64]) -> list[tuple[float, float, float]]:
        """The best (x, y, yaw) of distinct places, best first."""
        smooth = votes + np.roll(votes, -1, axis=1)  # a heading near a bin edge
        order = np.argsort(smooth.ravel())[::-1]
        out: list[tuple[float, float, float]] = []
        for flat in order[: 50 * self.n_hypotheses].tolist():
            p, b = divmod(flat, self.n_bins)
            x, y = self.grid[p]
            yaw = wrap_angle((b + 1.0) * self.yaw_bin)
            if any(
                math.hypot(x - hx, y - hy) < 2 * self.grid_m and abs(wrap_angle(yaw - hyaw)) < 0.3
                for hx, hy, hyaw in out
            ):
                continue
            out.append((float(x), float(y), yaw))
            if len(out) == self.n_hypotheses:
                break
        return out

    # ---------------------------------------------------------------------------- refine

    def _predict(
        self,
        r_wb: FloatArray,
        p_wb: FloatArray,
        cols: NDArray[np.int64] | None = None,
        points: FloatArray | None = None,
    ) -> FloatArray:
        """Unit bearings (body frame) of the landmarks (those of ``cols``, else all), or of
        ``points`` (world frame) instead."""
        pts = points if points is not None else self.points if cols is None else self.points[cols]
        d = (pts - p_wb) @ r_wb
        out: FloatArray = d / np.linalg.norm(d, axis=1, keepdims=True)
        return out

    def _associate(
        self, obs: FloatArray, r_wb: FloatArray, p_wb: FloatArray, angle: float
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Each observation's nearest predicted landmark within ``angle``, one-to-one."""
        pred = self._predict(r_wb, p_wb)
        rng = np.linalg.norm(self.points[:, :2] - p_wb[:2], axis=1) <= self.max_range_m
        cos = obs @ pred.T
        cos[:, ~rng] = -1.0
        best = np.argmax(cos, axis=1)
        ok = cos[np.arange(obs.shape[0]), best] >= math.cos(angle)
        rows, cols = np.flatnonzero(ok), best[ok]
        # one observation per landmark: the closest
        keep: dict[int, int] = {}
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            if c not in keep or cos[r, c] > cos[keep[c], c]:
                keep[c] = r
        cols = np.array(sorted(keep), dtype=np.int64)
        rows = np.array([keep[c] for c in cols.tolist()], dtype=np.int64)
        return rows, cols

    def _residuals(
        self, obs: FloatArray, rows: NDArray[np.int64], points: FloatArray, state: FloatArray
    ) -> FloatArray:
        """(n, 3): each pair's angular residual, observed bearing ``obs[rows]`` × the one
        predicted at ``state`` of its landmark at ``points`` (world frame)."""
        return cross_rows(obs[rows], self._predict(*self._pose(state), points=points))

    def _fit(
        self, obs: FloatArray, rows: NDArray[np.int64], cols: NDArray[np.int64], x0: FloatArray
    ) -> FloatArray:
        """(x, y, yaw) fitted to the pairs, robustly, the mower upright at the dock's camera
        height: three unknowns, not six — a free tilt and height let a wrong place explain
        many bearings by chance."""
        pts, o = self.points[cols], obs[rows]

        def residual(x: FloatArray) -> FloatArray:
            return self._residuals(obs, rows, pts, x).ravel()

        def jacobian(x: FloatArray) -> FloatArray:
            return self._residual_jacobian(o, pts, x)[1].reshape(-1, 3)

        sol = least_squares(residual, x0, jac=jacobian, loss="huber", f_scale=0.01, max_nfev=50)
        fitted: FloatArray = sol.x
        return fitted

    def _refine(
        self, obs: FloatArray, hyp: tuple[float, float, float]
    ) -> tuple[FloatArray, FloatArray, NDArray[np.int64], NDArray[np.int64]]:
        state = np.array(hyp, dtype=np.float64)
        for angle in (*np.radians([8.0, 5.0, 3.0, 2.0]), 1.5 * self.inlier_angle_rad):
            rows, cols = self._associate(obs, *self._pose(state), angle)
            if rows.size < 3:
                break
            state = self._fit(obs, rows, cols, state)
        r_wb, p_wb = self._pose(state)
        rows, cols = self._associate(obs, r_wb, p_wb, self.inlier_angle_rad)
        return r_wb, p_wb, rows, cols

    def _anneal(self, obs: FloatArray, state: FloatArray, sigmas: tuple[float, ...]) -> FloatArray:
        """(x, y, yaw) from ``state`` to a nearby maximum of the soft score: each bearing
        paired with its nearest landmark within 3 σ and weighed by the score's kernel
        exp(−θ²/2σ²) (a redescending loss: a feature beside a landmark's corner, or a pair
        with the corner's lattice neighbour, stops pulling), σ narrowed through ``sigmas``
        so that the wide start finds the basin and the narrow end its sharp optimum. A
        Huber fit does neither: measured from the true pose, it moved 1–2 cm to a pose the
        sharp score rated half as well."""
        for sigma in sigmas:
            for _ in range(self.ANNEAL_ROUNDS):
                rows, cols = self._associate(obs, *self._pose(state), 3.0 * sigma)
                if rows.size < 3:
                    return state
                pts = self.points[cols]
                norms = self._residual_norms(obs, rows, pts, state)
                root_w = np.exp(-(norms**2) / (4.0 * sigma**2))  # √ of the kernel
                state = self._weighted_fit(obs, rows, pts, root_w, state, max_nfev=20)
        return state

    def _weighted_fit(
        self,
        obs: FloatArray,
        rows: NDArray[np.int64],
        pts: FloatArray,
        root_w: FloatArray,
        x0: FloatArray,
        max_nfev: int = 50,
    ) -> FloatArray:
        """(x, y, yaw) by least squares over the pairs' residuals, each pair's scaled by its
        ``root_w``: Gauss–Newton with the closed-form Jacobian (:meth:`_residual_jacobian`),
        a step that raises the cost shortened Levenberg–Marquardt's way, at most
        ``max_nfev`` steps."""
        o = obs[rows]
        w2 = np.broadcast_to((root_w**2)[:, None], (len(rows), 3))
        x = np.asarray(x0, dtype=np.float64).copy()
        r, jac = self._residual_jacobian(o, pts, x)
        cost = float(np.sum(w2 * r * r))
        damping = 0.0
        for _ in range(max_nfev):
            normal = np.einsum("nr,nri,nrj->ij", w2, jac, jac)
            grad = np.einsum("nr,nri,nr->i", w2, jac, r)
            try:
                step = -np.linalg.solve(normal + damping * np.diag(np.diag(normal)), grad)
            except np.linalg.LinAlgError:
                break
            if float(np.linalg.norm(step)) <= self.FIT_XTOL * (
                self.FIT_XTOL + float(np.linalg.norm(x))
            ):
                break
            r_new, jac_new = self._residual_jacobian(o, pts, x + step)
            cost_new = float(np.sum(w2 * r_new * r_new))
            if not cost_new <= cost:  # Levenberg–Marquardt: a bad step is shortened
                damping = max(1e-3, 10.0 * damping)
                continue
            x, r, jac = x + step, r_new, jac_new
            done = cost - cost_new <= self.FIT_XTOL * cost
            cost, damping = cost_new, 0.1 * damping
            if done:
                break
        return x

    #: the fits stop at a step this small relative to the pose, or a fall in cost this small
    #: relative to the cost
    FIT_XTOL = 1e-8

    def _residual_jacobian(
        self, o: FloatArray, pts: FloatArray, state: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """The pairs' residuals o × p (:meth:`_residuals`, ``o`` the paired bearings) and
        their derivative with respect to (x, y, heading), (n, 3, 3), in closed form: with
        d = R(ψ)ᵀ (L − P) and p = d/|d|, ∂d/∂x = −R(ψ)ᵀ e_x, ∂d/∂y = −R(ψ)ᵀ e_y,
        ∂d/∂ψ = (d_y, −d_x, 0), ∂p/∂d = (I − p pᵀ)/|d|."""
        r_wb, p_wb = self._pose(state)
        d = (pts - p_wb) @ r_wb
        norm = np.linalg.norm(d, axis=1)
        p = d / norm[:, None]
        dd = np.zeros((d.shape[0], 3, 3))  # (n, component of d, pose)
        dd[:, :, 0] = -r_wb[0]  # −Rᵀ e_x: the first row of R
        dd[:, :, 1] = -r_wb[1]
        dd[:, 0, 2], dd[:, 1, 2] = d[:, 1], -d[:, 0]
        dp = (dd - p[:, :, None] * np.einsum("nk,nki->ni", p, dd)[:, None, :]) / norm[:, None, None]
        return cross_rows(o, p), _cross_rows_jac(o, dp)

    #: the local search around the chosen place: ± this far and turned, in these steps
    POLISH_M, POLISH_STEP_M = 0.5, 0.05
    POLISH_RAD, POLISH_STEP_RAD = math.radians(4.0), math.radians(1.0)
    #: the soft score's angular scale at its sharpest (a frame whose bearings are worse is
    #: scored at their own σ: :meth:`_frame_sigma`): a bearing counts exp(−θ²/2σ²) towards
    #: its landmark. Sharp — a corner's bearing is good to a few hundredths of a degree at
    #: pixel level — so that a pose that pairs bearings with a board corner's lattice
    #: neighbours (0.4 m apart: 2–4° at 6–12 m), a few tenths of a degree off each, scores
    #: far below the true pose (measured: 5–8 against 10–17); on the polish grid a wider
    #: one (a grid pose is up to half a step off)
    SOFT_SIGMA_RAD = math.radians(0.1)
    GRID_SIGMA_RAD = math.radians(1.0)
    #: the polish refines the best poses of its grid that are ≥ 2 steps apart, and the best
    #: local maxima of the grid among the rest (another basin: a true pose that the best
    #: few, all in one wrong basin, would never reach)
    POLISH_CANDIDATES = 10
    POLISH_PEAKS = 5
    #: the refinement anneals its kernel through these, then to the frame's σ, two rounds each
    ANNEAL_SIGMAS_RAD = tuple(math.radians(v) for v in (1.0, 0.5, 0.25))
    ANNEAL_ROUNDS = 2
    #: a frame's bearings are judged no sharper than this (a camera's worse ones widen it)
    MAX_FRAME_SIGMA_RAD = math.radians(0.5)

    def _frame_sigma(self, obs: FloatArray, candidates: list[FloatArray]) -> float:
        """The soft score's σ for this frame: the bearings' own σ per axis, robustly from
        the inliers of whichever candidate fits its inliers sharpest (the true pose, when
        it is among them: a pose paired with lattice neighbours fits worse), no less than
        :data:`SOFT_SIGMA_RAD` — a camera whose bearings are 0.2° off scored at 0.1° makes
        every pose's score a few lucky pairs."""
        best = self.MAX_FRAME_SIGMA_RAD
        for cand in candidates:
            rows, cols = self._associate(obs, *self._pose(cand), self.inlier_angle_rad)
            if rows.size >= self.min_inliers:
                norms = self._residual_norms(obs, rows, self.points[cols], cand)
                best = min(best, self._rayleigh_sigma(norms))
        return max(self.SOFT_SIGMA_RAD, best)

    #: a pose this far from the best, or turned this much from it, that scores nearly as
    #: well: the place is not pinned down. Turned too: the corners of a board are a lattice
    #: (0.4 m apart), and a turn by one lattice step with a few centimetres' shift pairs
    #: each bearing with its landmark's neighbour — measured at pixel level, paper lawn,
    #: the true pose and one 0.1 m and 2.4° off, each with 27 inliers, the wrong one
    #: scoring 4 % better, accepted and permitted
    LOCAL_AMBIGUITY_M = 0.15
    LOCAL_AMBIGUITY_RAD = math.radians(1.0)
    LOCAL_AMBIGUITY_RATIO = 0.9

    def soft_score(self, obs: FloatArray, state: FloatArray, sigma: float | None = None) -> float:
        """Σ over bearings of exp(−θ²/2σ²), θ the angle to the nearest predicted landmark."""
        cos = (obs @ self._predict(*self._pose(state)).T).max(axis=1)
        theta2 = 2.0 * (1.0 - np.clip(cos, -1.0, 1.0))
        sig = self.SOFT_SIGMA_RAD if sigma is None else sigma
        return float(np.exp(-theta2 / (2 * sig**2)).sum())

    def _grid_scores(
        self, obs: FloatArray, state: FloatArray, step: FloatArray, turn: FloatArray
    ) -> FloatArray:
        """The soft score (σ :data:`GRID_SIGMA_RAD`) of every pose of the polish grid —
        ``state`` shifted by every (``step``, ``step``) and turned by every ``turn``, in
        ``np.meshgrid(x, y, yaw, indexing="ij")`` order — counting for each bearing only the
        landmarks that could come near it from some pose of the grid: seen from the grid's
        centre within asin(shift/range) + the largest turn + 6 σ of it (a camera shifted by
        ``shift`` sees a point at ``range`` at most that much elsewhere; a landmark farther
        off adds less than e⁻¹⁸ to any pose's score). A pose's cosine to a landmark splits
        into where the camera is (a unit vector per position) and how it is turned (the
        bearing in the world per heading): positions × headings × the pairs that can
        match, as small matrix products, never poses × bearings × landmarks."""
        half = float(np.abs(step).max())
        pts = self.points[np.hypot(*(self.points[:, :2] - state[:2]).T) <= self.max_range_m + half]
        r_wb, p_wb = self._pose(state)
        dist = np.linalg.norm(pts - p_wb, axis=1)
        moved = np.arcsin(np.minimum(1.0, math.sqrt(2.0) * half / np.maximum(dist, 1e-9)))
        bound = moved + float(np.abs(turn).max()) + 6.0 * self.GRID_SIGMA_RAD
        centre = np.clip(obs @ self._predict(r_wb, p_wb, points=pts).T, -1.0, 1.0)  # (M, N)
        m_idx, n_idx = np.nonzero(np.arccos(centre) <= bound[None, :])  # sorted by bearing
        n_pos, n_yaw = step.size**2, turn.size
        if m_idx.size == 0:
            return np.zeros(n_pos * n_yaw)
        used, n_local = np.unique(n_idx, return_inverse=True)
        gx, gy = np.meshgrid(state[0] + step, state[1] + step, indexing="ij")
        cam = np.c_[gx.ravel(), gy.ravel(), np.full(n_pos, self.height)]
        to_lm = pts[used][:, None, :] - cam[None, :, :]  # (U, positions, 3) world
        to_lm /= np.linalg.norm(to_lm, axis=-1, keepdims=True)
        yaw = state[2] + turn
        c, s = np.cos(yaw), np.sin(yaw)
        o = obs[m_idx]  # (Q, 3) body; in the world at each heading: (Q, 3, headings)
        world = np.stack(
            [
                c * o[:, :1] - s * o[:, 1:2],
                s * o[:, :1] + c * o[:, 1:2],
                np.repeat(o[:, 2:], n_yaw, axis=1),
            ],
            axis=1,
        )
        cos = to_lm[n_local] @ world  # (Q, positions, headings)
        starts = np.flatnonzero(np.r_[True, m_idx[1:] != m_idx[:-1]])
        best = np.maximum.reduceat(cos, starts, axis=0)  # each bearing's nearest landmark
        theta2 = 2.0 * (1.0 - np.clip(best, -1.0, 1.0))  # ≈ θ² for small angles
        score: FloatArray = np.exp(-theta2 / (2 * self.GRID_SIGMA_RAD**2)).sum(axis=0)
        return score.ravel()

    def _polish(
        self, obs: FloatArray, state: FloatArray
    ) -> tuple[FloatArray, float, FloatArray | None, float]:
        """Refinement from one start can stop in a local optimum a few decimetres off (two
        frames then agree on the same wrong pose), where the true pose explains the bearings
        much better at sub-degree precision. Every pose of a fine grid around it is scored
        at once (soft score at the grid's precision), the best few and the best other local
        maxima are refined (:meth:`_anneal`), and the one with the best sharp soft score is
        kept; with it, how well the best optimum more than
        :data:`LOCAL_AMBIGUITY_M` away or turned more than :data:`LOCAL_AMBIGUITY_RAD` does
        (the ratio of their sharp soft scores), and that optimum."""
        d = np.arange(-self.POLISH_M, self.POLISH_M + 1e-9, self.POLISH_STEP_M)
        dyaw = np.arange(-self.POLISH_RAD, self.POLISH_RAD + 1e-9, self.POLISH_STEP_RAD)
        gx, gy, gyaw = np.meshgrid(state[0] + d, state[1] + d, state[2] + dyaw, indexing="ij")
        poses = np.column_stack([gx.ravel(), gy.ravel(), gyaw.ravel()])  # (K, 3)
        score = self._grid_scores(obs, state, d, dyaw)
        order = np.argsort(score)[::-1]
        starts: list[FloatArray] = []
        for k in order.tolist():
            if all(np.hypot(*(poses[k, :2] - q[:2])) > 2 * self.POLISH_STEP_M for q in starts):
                starts.append(poses[k])
            if len(starts) == self.POLISH_CANDIDATES:
                break
        cube = score.reshape(d.size, d.size, dyaw.size)
        peak = (cube >= maximum_filter(cube, size=3, mode="nearest")).ravel()
        taken = {tuple(q) for q in starts}
        peaks = [poses[k] for k in order[peak[order]].tolist() if tuple(poses[k]) not in taken]
        starts += peaks[: self.POLISH_PEAKS]
        coarse = [self._anneal(obs, start, self.ANNEAL_SIGMAS_RAD) for start in starts]
        sigma = self._frame_sigma(obs, coarse)
        annealed = [self._anneal(obs, cand, (sigma,)) for cand in coarse]
        refined = [(self.soft_score(obs, cand, sigma), cand) for cand in annealed]
        refined.sort(key=lambda r: -r[0])
        top, best = refined[0]
        # the rival: the best refined optimum elsewhere, judged at the same sharp precision
        others = [
            (sc, c)
            for sc, c in refined[1:]
            if np.hypot(*(c[:2] - best[:2])) > self.LOCAL_AMBIGUITY_M
            or abs(wrap_angle(float(c[2] - best[2]))) > self.LOCAL_AMBIGUITY_RAD
        ]
        if not others or top <= 0:
            return best, 0.0, None, sigma
        rival_score, rival = max(others, key=lambda r: r[0])
        return best, rival_score / top, rival, sigma

    #: every bearing counts as at least this far off (rad): the trust gate (:meth:`_trusted`)
    #: and the final fit's Huber weights take the residuals' robust σ as at least this (a
    #: frame fitted unusually well must not gate out or down-weigh its good pairs), and so
    #: does a bearing's σ in the answer's covariance (:meth:`covariance`). One floor since
    #: stop 70: the gate's was 0.1°, and a standing frame's few features beside their
    #: corners, 0.1–0.45° off among bearings 0.01–0.03° off, kept their full weight and pulled
    #: the answer 5–23 mm at σ 2–4 mm (look-alike lawn, each answer fitted again to the true
    #: landmarks: README, issue 18); the covariance's at 0.1° made the answers wider than their
    #: errors (stop 53: NEES 1.5–1.9 right after the answer). 0.05° (stop 70, set against the
    #: old renderer's 0.055° rms) bound on every standing answer once the renderer drew the
    #: panels where they are (stop 76: the residuals' robust σ 0.008–0.034°, look-alike
    #: lawn): their σ was 1.1–1.5× their errors (z² per component 0.45–0.83,
    #: pixel pools, map's frame). At 0.025° the answers are also closer (the gate and the
    #: weights sharper: 1.35 → 1.11 mm rms) and their z² 0.66–1.43 over both lawns; 0.015°
    #: left the paper lawn's over (1.04–1.86) and 0.035° the look-alike's under (0.53–0.66)
    BEARING_FLOOR_RAD = math.radians(0.025)
    #: the answer's fit (:meth:`_final_fit`): Huber weights at this many robust σ (95 %
    #: efficient on Gaussian errors), a few reweighting rounds
    HUBER_K = 1.345
    FINAL_ROUNDS = 4

    @staticmethod
    def _rayleigh_sigma(norms: FloatArray) -> float:
        """The bearings' σ per axis from residual norms, robustly: a residual has two free
        directions, its norm's median is σ·√(2 ln 2) (Rayleigh) — a few pairs a degree
        off (a corner next to the landmark's) do not move it."""
        return float(np.median(norms)) / math.sqrt(2.0 * math.log(2.0))

    def _robust_sigma(self, norms: FloatArray) -> float:
        """:meth:`_rayleigh_sigma`, at least :data:`BEARING_FLOOR_RAD`."""
        return max(self.BEARING_FLOOR_RAD, self._rayleigh_sigma(norms))

    def _residual_norms(
        self, obs: FloatArray, rows: NDArray[np.int64], points: FloatArray, state: FloatArray
    ) -> FloatArray:
        """Each pair's angular residual's norm (rad): :meth:`_residuals`, per row."""
        out: FloatArray = np.linalg.norm(self._residuals(obs, rows, points, state), axis=1)
        return out

    def _final_fit(
        self, obs: FloatArray, rows: NDArray[np.int64], cols: NDArray[np.int64], x0: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """The answer's (x, y, heading): the given pairs' least squares, each pair weighted
        by Huber at :data:`HUBER_K` robust σ of its residual's norm (iteratively reweighted).
        :meth:`locate` gives it the inliers :meth:`_trusted` keeps; the inlier angle (1°) is
        ten times the bearings' own error, and a feature beside the landmark, 0.5–1° off,
        would otherwise weigh as much as a true corner (measured, pixel level: answers 2–4 cm
        and 0.1° off at σ 7–10 mm, the true pose fitting the inliers better than the answer
        did). And the weights, for :meth:`covariance`."""
        pts = self.points[cols]

        def huber_weights(state: FloatArray) -> FloatArray:
            norms = self._residual_norms(obs, rows, pts, state)
            scale = self.HUBER_K * self._robust_sigma(norms)
            out: FloatArray = np.minimum(1.0, scale / np.maximum(norms, 1e-12))
            return out

        state = x0
        for _ in range(self.FINAL_ROUNDS):
            state = self._weighted_fit(obs, rows, pts, np.sqrt(huber_weights(state)), state)
        return state, huber_weights(state)

    #: the consensus search (:meth:`_consensus`): this many fits to two inlier pairs each
    CONSENSUS_DRAWS = 16

    def _consensus(
        self,
        obs: FloatArray,
        rows: NDArray[np.int64],
        cols: NDArray[np.int64],
        state: FloatArray,
        sigma: float,
    ) -> FloatArray:
        """The sharp soft score's best optimum among the inliers' own poses: each of
        :data:`CONSENSUS_DRAWS` pairs of inliers (drawn reproducibly) fitted exactly, refined
        (:meth:`_anneal` at the frame's ``sigma``) and scored; ``state`` unless one scores
        higher. Where a fifth to two fifths of the inliers are features beside their
        landmarks' corners, 0.4–1° off, the polish's anneal (from a 1° kernel down) can end
        in their basin (measured, paper lawn, a kidnap: 38 mm and 0.26° off at σ 9 mm and
        0.055°, the true pose scoring 12.1 against its 10.9); two right pairs alone land in
        the true one (2 mm, 0.003°)."""
        best, best_score = state, self.soft_score(obs, state, sigma)
        if rows.size < 2:
            return best
        rng = np.random.default_rng(rows.size)
        for _ in range(self.CONSENSUS_DRAWS):
            pick = rng.choice(rows.size, 2, replace=False)
            pts = self.points[cols[pick]]
            cand = self._weighted_fit(obs, rows[pick], pts, np.ones(2), state, max_nfev=20)
            cand = self._anneal(obs, cand, (sigma,))
            score = self.soft_score(obs, cand, sigma)
            if score > best_score:
                best, best_score = cand, score
        return best

    #: an inlier the fit trusts (a filter's first association, :meth:`Relocalization.seeds`)
    #: has its residual inside this χ²₂ gate at the residuals' robust σ
    TRUST_GATE = 0.99

    def _trusted(
        self, obs: FloatArray, rows: NDArray[np.int64], cols: NDArray[np.int64], state: FloatArray
    ) -> NDArray[np.bool_]:
        """Which inliers lie inside :data:`TRUST_GATE` of the pose ``state``: the rest,
        within the inlier angle yet many robust σ off, are mostly features beside the
        landmark's corner, and the answer's fit leaves them out (Huber alone still gave the
        eleven such of 27 inliers a third of a weight each: they pulled the answer 0.26° off
        the optimum :meth:`_consensus` had found)."""
        norms = self._residual_norms(obs, rows, self.points[cols], state)
        sigma = self._robust_sigma(norms)
        out: NDArray[np.bool_] = norms**2 <= chi2.ppf(self.TRUST_GATE, df=2) * sigma**2
        return out

    def covariance(
        self,
        obs: FloatArray,
        rows: NDArray[np.int64],
        cols: NDArray[np.int64],
        state: FloatArray,
        weights: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """The (x, y, heading) covariance of a pose fitted to the inliers with ``weights``
        (:meth:`_final_fit`; default all 1) over their angular residuals (linearised, J in
        closed form: :meth:`_residual_jacobian`). A bearing's σᵢ² is its landmark's position
        variance seen from the pose (σ²_landmark / range²: the map's errors move the answer
        too) plus the
        bearings' own noise — the residuals' robust variance per axis beyond the map's mean
        part — and at least what its own residual shows (a pair the weights doubt is as far
        off as it looks), at least :attr:`BEARING_FLOOR_RAD` squared. And how much the map's
        errors move it: the cross-covariance with the inliers' landmark positions (J_L: the
        residual's derivative with respect to the landmark; P_L its map covariance),
        (3, 3·n) in the inliers' order."""

        pts = self.points[cols]
        w = np.ones(rows.size) if weights is None else weights

        def at(points: FloatArray) -> FloatArray:
            return self._residuals(obs, rows, points, state)

        r0, jac = self._residual_jacobian(obs[rows], pts, state)  # jac: (n, residual, pose)
        # each residual depends on its own landmark only: one shift of all of them per axis
        jac_l = np.empty((r0.shape[0], 3, 3))  # (n, residual, landmark axis)
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-4
            jac_l[:, :, k] = (at(pts + d) - at(pts - d)) / 2e-4
        norms = np.linalg.norm(r0, axis=1)
        s2 = self._robust_sigma(norms) ** 2
        _, p_wb = self._pose(state)
        range2 = np.sum((pts - p_wb) ** 2, axis=1)
        seen_from_here = self._point_var[cols] / np.maximum(range2, 0.25)  # the map's part
        # the residuals show the map's errors too: the bearings' own noise is what they
        # show beyond them (moments: E[s²] = noise² + mean map part), not all of it again
        noise2 = max(0.0, s2 - float(seen_from_here.mean()))
        own = 0.5 * norms**2  # per axis: a residual's two free directions
        var = np.maximum(np.maximum(noise2 + seen_from_here, own), self.BEARING_FLOOR_RAD**2)
        # the fit's error is −A (n + J_L δL) with A = (Σ wᵢ Jᵢᵀ Jᵢ)⁻¹ [wᵢ Jᵢᵀ], so its
        # covariance is A diag(σᵢ²) Aᵀ (a sandwich) …
        gain = np.linalg.pinv(np.einsum("nri,nrj,n->ij", jac, jac, w))
        spread = np.einsum("nri,nrj,n->ij", jac, jac, w * w * var)
        cov: FloatArray = gain @ spread @ gain
        # … and its cross-covariance with landmark i's position −A wᵢ Jᵢᵀ J_Lᵢ P_Lᵢ
        jt_jl_pl = np.einsum("nri,nrk,nkl,n->nil", jac, jac_l, self._point_cov[cols], w)
        cross: FloatArray = -gain @ np.transpose(jt_jl_pl, (1, 0, 2)).reshape(3, -1)
        return cov, cross

    def _pose(self, state: FloatArray) -> tuple[FloatArray, FloatArray]:
        return yaw_rotation(float(state[2])), np.array([state[0], state[1], self.height])

    # ---------------------------------------------------------------------------- answer

    @staticmethod
    def _near(p_wb: FloatArray, r_wb: FloatArray, prior: tuple[float, float, float]) -> bool:
        """An optimum that answers for the prior: one within :data:`DISTINCT_M` and
        :data:`DISTINCT_RAD` of it, whichever start it was refined from — the refinement
        from the prior itself can stop in a local optimum a few decimetres off (measured on
        the bench after a restart: 0.3 m and 7° off with σ 2 cm) that the places voted for
        over the whole map find better; and it can wander away from the prior, where it is
        no answer *for the prior* (measured on the bench: killed while turning on the spot,
        the mower finished its turn, 18° more, before it stopped; the refinement from the
        saved pose ended 0.25 m and 15° from it, 3° from the truth, and counted as the
        prior's answer for having started there — accepted and permitted; replayed on that
        map's rendered view from 1,100 priors around it, 2 such wrong poses, none now)."""
        yaw = math.atan2(r_wb[1, 0], r_wb[0, 0])
        close = math.hypot(float(p_wb[0]) - prior[0], float(p_wb[1]) - prior[1]) <= DISTINCT_M
        return close and abs(wrap_angle(yaw - prior[2])) <= DISTINCT_RAD

    def _beaten(self, n_prior: int, n_rival: int) -> bool:
        """A rival place explains clearly more bearings than the prior's answer: more than
        the ambiguity rule would call a tie seen from the rival (a look-alike twin of the
        true place explains its look-alike landmarks, never clearly more)."""
        tie = n_prior > self.ambiguity_ratio * n_rival and n_rival - n_prior < self.ambiguity_margin
        return n_rival > n_prior and not tie

    def locate(
        self,
        bearings: FloatArray,
        near: tuple[float, float, float] | None = None,
        heading: tuple[float, float] | None = None,
    ) -> Relocalization:
        """The pose from one frame's body-frame unit bearings (module doc); ``near``: a
        prior (x, y, heading) to check — the refinement starts there, the answer is the best
        optimum near it, and the whole map's vote still runs for rival places (module doc);
        ``heading``: the compass's (ψ, σ), for a search of the whole map."""
        t0 = time.perf_counter()
        obs = np.asarray(bearings, dtype=np.float64).reshape(-1, 3)
        obs = obs / np.linalg.norm(obs, axis=1, keepdims=True)

        def done(why: str, n: int = 0, rival: bool = False) -> Relocalization:
            ms = 1e3 * (time.perf_counter() - t0)
            return Relocalization(False, hypotheses=n, ms=ms, why=why, rival=rival)

        if obs.shape[0] < self.min_inliers or self.points.shape[0] < self.min_inliers:
            return done(f"{obs.shape[0]} bearings, {self.points.shape[0]} landmarks")
        azimuth = np.arctan2(obs[:, 1], obs[:, 0])
        elevation = np.arctan2(obs[:, 2], np.hypot(obs[:, 0], obs[:, 1]))
        # the compass's heading and tolerance, when a search of the whole map may use it
        tol = self.compass_tolerance(heading) if near is None else None
        compass = (heading[0], tol) if heading is not None and tol is not None else None
        votes = self._votes(azimuth, elevation)
        if compass is not None:
            self._within_compass(votes, *compass)
        hyps = self._hypotheses(votes)
        if near is not None:  # the prior's own optimum first; the places voted for: rivals
            hyps = [near, *hyps]
        scored = []
        for hyp in hyps:
            r_wb, p_wb, rows, cols = self._refine(obs, hyp)
            # the angular residual of the inliers breaks ties between nearby local optima
            spread = (
                float(
                    np.mean(
                        np.linalg.norm(np.cross(obs[rows], self._predict(r_wb, p_wb, cols)), axis=1)
                    )
                )
                if rows.size
                else 1.0
            )
            scored.append((int(rows.size), r_wb, p_wb, rows, cols, spread))
        if near is not None and not any(
            n >= self.min_inliers and self._near(p, r, near) for n, r, p, *_ in scored
        ):
            near = None  # nothing near the prior explains enough: judged as a whole-map search
        if near is None:
            scored.sort(key=lambda s: (-s[0], s[5]))
        else:  # the answer is the best optimum near the prior; every other one is a rival
            scored.sort(key=lambda s: (not self._near(s[2], s[1], near), -s[0], s[5]))
        n_best, r_wb, p_wb, rows, cols, _ = scored[0]
        yaw0 = math.atan2(r_wb[1, 0], r_wb[0, 0])
        unpolished = np.array([p_wb[0], p_wb[1], yaw0])
        state, rival, rival_pose, sigma = self._polish(obs, unpolished)
        if self.soft_score(obs, state, sigma) >= self.soft_score(obs, unpolished, sigma):
            r_wb, p_wb = self._pose(state)
            rows, cols = self._associate(obs, r_wb, p_wb, self.inlier_angle_rad)
            n_best = int(rows.size)
        yaw_best = math.atan2(r_wb[1, 0], r_wb[0, 0])
        runner = beside = 0  # the best other place; the best other pose near this one
        for n, r2, p2, *_ in scored[1:]:
            moved = float(np.linalg.norm(p2[:2] - p_wb[:2]))
            yaw2 = math.atan2(r2[1, 0], r2[0, 0])
            turned = abs(wrap_angle(yaw2 - yaw_best))
            if compass is not None and abs(wrap_angle(yaw2 - compass[0])) > compass[1]:
                continue  # a place the compass rules out is no rival
            if moved > DISTINCT_M or turned > DISTINCT_RAD:
                runner = max(runner, n)
            elif moved > self.LOCAL_AMBIGUITY_M or turned > self.LOCAL_AMBIGUITY_RAD:
                beside = max(beside, n)
        if n_best < self.min_inliers:
            return done(f"{n_best} inliers (need {self.min_inliers})", len(hyps))
        if compass is not None:
            psi, tolerance = compass
            off = abs(wrap_angle(yaw_best - psi))
            if off > tolerance:
                return done(
                    f"the compass says {math.degrees(psi):.0f}°, the best place faces "
                    f"{math.degrees(yaw_best):.0f}° ({math.degrees(off):.0f}° off, "
                    f"tolerance {math.degrees(tolerance):.0f}°)",
                    len(hyps),
                )
        if near is not None:
            if self._beaten(n_best, runner):
                return done(
                    f"the prior does not hold: {n_best} inliers near it, {runner} at another place",
                    len(hyps),
                    rival=True,
                )
            if self._beaten(n_best, beside):  # a better pose beside the prior's answer
                return done(
                    f"the prior's answer is not the best pose there: {n_best} inliers, "
                    f"{beside} at a pose beside it",
                    len(hyps),
                    rival=True,
                )
        elif runner > self.ambiguity_ratio * n_best and n_best - runner < self.ambiguity_margin:
            return done(
                f"ambiguous: {n_best} inliers here, {runner} at another place (standing still "
                "keeps the same view: moving or turning the mower may tell them apart)",
                len(hyps),
                rival=True,
            )
        if rival > self.LOCAL_AMBIGUITY_RATIO and rival_pose is not None:
            moved = float(np.hypot(*(rival_pose[:2] - state[:2])))
            turn = math.degrees(abs(wrap_angle(float(rival_pose[2] - state[2]))))
            return done(
                f"not pinned down: a pose {moved:.2f} m away and turned {turn:.1f}° fits "
                f"{rival:.0%} as well",
                len(hyps),
                rival=True,
            )
        to_lm = self.points[cols] - p_wb
        az = np.sort(np.arctan2(to_lm[:, 1], to_lm[:, 0]))
        gaps = np.diff(np.concatenate([az, az[:1] + 2 * math.pi]))
        if 2 * math.pi - gaps.max() < MIN_AZIMUTH_SPREAD_RAD:
            return done("inliers all on one side", len(hyps))
        start = self._consensus(obs, rows, cols, np.array([p_wb[0], p_wb[1], yaw_best]), sigma)
        trusted = self._trusted(obs, rows, cols, start)
        if trusted.sum() < self.min_inliers:
            trusted = np.ones(rows.size, dtype=bool)
        fitted, weights = self._final_fit(obs, rows[trusted], cols[trusted], start)
        r_wb, p_wb = self._pose(fitted)
        cov, cross_trusted = self.covariance(obs, rows[trusted], cols[trusted], fitted, weights)
        cross = np.zeros((3, 3 * rows.size))  # the doubted pairs' landmarks: not in the fit
        cross.reshape(3, -1, 3)[:, trusted, :] = cross_trusted.reshape(3, -1, 3)
        return Relocalization(
            True,
            r_wb,
            p_wb,
            [(int(r), int(self.ids[c])) for r, c in zip(rows, cols, strict=True)],
            runner,
            len(hyps),
            1e3 * (time.perf_counter() - t0),
            covariance=cov,
            landmark_cross=cross,
            trusted=trusted,
        )
