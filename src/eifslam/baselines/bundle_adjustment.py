"""Full bundle adjustment: the paper's SBA comparison (pure NumPy / SciPy).

Every track seen in at least two posed frames (both ``Ωp`` and ``Ωm``: "every track in
the map") becomes a 3-D point, triangulated from the current pose estimates; then all
poses and points are adjusted to minimise the reprojection error of every image
measurement with :func:`scipy.optimize.least_squares` (``method="trf"``, analytic sparse
Jacobian from :func:`eifslam.geometry.models.feature_model`, ``x_scale="jac"``, Huber loss).

Parameters
----------
A pose is its current estimate ``(p0, q0)`` plus an increment ``[dp (3), phi (3)]`` with
``p = p0 + dp`` and ``q = q0 ⊗ Exp(phi)`` (``phi`` a rotation vector in the camera frame,
the convention of :meth:`eifslam.estimation.filter.InformationFilter.pose_covariance`). A point is
its position ``X`` (3).

Gauge
-----
Monocular BA leaves a similarity (7 DoF) free. The first pose (``gauge`` pair, first
index) is held fixed (its 6 parameters are removed), and one coordinate of the second
pose's position, the one along which it lies furthest from the first, is held fixed too
(it fixes the scale). After the optimisation the whole solution is scaled about the
first pose so that the distance between the two gauge poses equals its initial value
(a similarity: the reprojection errors do not change). So the output keeps the first pose
and the first baseline's length, exactly like the filter's gauge priors.

The data come in as arrays (:class:`Observations`); :func:`observations_from_frontend`
reads them from a :class:`~eifslam.frontend.FrontEnd` without importing it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ..geometry import models
from ..geometry.camera import PinholeCamera
from ..errors import ConfigError, EstimatorError
from ..geometry.rotations import quat_exp, quat_left_matrix, quat_normalize
from ..estimation.initialisation import triangulate

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class BAConfig:
    """Settings of :func:`bundle_adjust`.

    Attributes
    ----------
    solver : {"schur", "trf"}
        ``"schur"``: Levenberg-Marquardt with the points eliminated by the Schur complement
        (SBA's algorithm, :func:`solve_schur_lm`, Huber loss by reweighting);
        ``"trf"``: :func:`scipy.optimize.least_squares` (``method="trf"``, ``lsmr``).
    loss : str
        ``least_squares`` loss (``"trf"`` only; ``"schur"`` always uses Huber) (``"huber"``, ``"soft_l1"``, ``"cauchy"``, ``"linear"``...).
    robust_px : float
        Residual (pixels, for ``sigma_px = 1``) where the robust loss departs from
        quadratic (``f_scale`` in whitened units is ``robust_px / median(sigma_px)``).
    max_nfev : int
        At most this many residual evaluations (``"trf"``) or LM steps (``"schur"``).
    ftol, xtol, gtol : float
        ``least_squares`` stopping tolerances.
    min_parallax_deg : float
        A track becomes a point only if the rays of its two most distant views differ by
        at least this angle.
    max_initial_px : float
        Observations whose reprojection error at the initial estimate exceeds this are
        left out (gross outliers, wrong triangulations).
    """

    solver: str = "schur"
    loss: str = "huber"
    robust_px: float = 2.0
    max_nfev: int = 100
    ftol: float = 1e-8
    xtol: float = 1e-10
    gtol: float = 1e-10
    min_parallax_deg: float = 0.5
    max_initial_px: float = 3.0

    def __post_init__(self) -> None:
        for key in ("robust_px", "ftol", "xtol", "gtol", "max_initial_px"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"ba.{key} must be a positive number, got {v!r}")
        if self.solver not in ("schur", "trf"):
            raise ConfigError(f"ba.solver must be 'schur' or 'trf', got {self.solver!r}")
        if self.max_nfev < 1:
            raise ConfigError("ba.max_nfev must be at least 1")
        if not self.min_parallax_deg >= 0:
            raise ConfigError("ba.min_parallax_deg must be >= 0")


@dataclass(frozen=True)
class Observations:
    """Image measurements of tracks.

    Attributes
    ----------
    frame : (N,) int64, frame id of the image.
    track : (N,) int64, track id.
    uv : (N, 2) float64, undistorted pixels.
    sigma_px : (N,) float64, standard deviation of each pixel coordinate.
    """

    frame: IntArray
    track: IntArray
    uv: Array
    sigma_px: Array

    def __len__(self) -> int:
        return int(len(self.frame))


@dataclass
class BAResult:
    """What :func:`bundle_adjust` returns.

    Attributes
    ----------
    frame_ids : (P,) int64; positions : (P, 3); quats : (P, 4) unit ``q_wc``.
    track_ids : (M,) int64; points : (M, 3) world frame.
    n_observations : int, image measurements in the problem.
    iterations : int, residual evaluations (``nfev``) of ``least_squares``.
    seconds : float, triangulation + optimisation wall time.
    initial_rms_px, final_rms_px : float, RMS reprojection error over all observations.
    success : bool; message : str, from ``least_squares``.
    """

    frame_ids: IntArray
    positions: Array
    quats: Array
    track_ids: IntArray
    points: Array
    n_observations: int
    iterations: int
    seconds: float
    initial_rms_px: float
    final_rms_px: float
    success: bool
    message: str

    @property
    def n_points(self) -> int:
        return int(len(self.track_ids))

    def summary(self) -> dict:
        """JSON-ready figures (``report.json``'s ``ba`` section)."""
        return dict(n_points=self.n_points, n_observations=self.n_observations, iterations=self.iterations,
                    seconds=round(self.seconds, 3), initial_rms_px=self.initial_rms_px,
                    final_rms_px=self.final_rms_px, success=self.success, message=self.message)


# -- pose increments ----------------------------------------------------------------------
def exp_jacobian(phi: Array) -> Array:
    """``d Exp(phi) / d phi`` of the unit quaternion of rotation vectors ``phi`` (N, 3) -> (N, 4, 3)."""
    th = np.linalg.norm(phi, axis=1)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    s = np.where(small, 0.5 - th**2 / 48.0, np.sin(0.5 * ts) / ts)  # sin(th/2)/th
    ds = np.where(small, -1.0 / 24.0, (0.5 * np.cos(0.5 * ts) * ts - np.sin(0.5 * ts)) / ts**3)  # (ds/dth)/th
    J = np.zeros((len(phi), 4, 3))
    J[:, 0, :] = -0.5 * s[:, None] * phi
    J[:, 1:, :] = s[:, None, None] * np.eye(3) + ds[:, None, None] * phi[:, :, None] * phi[:, None, :]
    return J


def apply_increment(p0: Array, q0: Array, d: Array) -> tuple[Array, Array]:
    """Poses ``(p0 + dp, q0 ⊗ Exp(phi))`` for increments ``d = [dp, phi]`` (P, 6)."""
    L = quat_left_matrix(q0)
    return p0 + d[:, :3], np.einsum("nij,nj->ni", L, quat_exp(d[:, 3:]))


# -- the problem ----------------------------------------------------------------------------
class _Problem:
    """Index bookkeeping, residuals and the sparse Jacobian of one BA problem."""

    def __init__(self, camera: PinholeCamera, p0: Array, q0: Array, X0: Array, pose_idx: IntArray,
                 point_idx: IntArray, uv: Array, sigma: Array, gauge: tuple[int, int]) -> None:
        self.cam, self.p0, self.q0, self.uv, self.w = camera, p0, q0, uv, 1.0 / sigma
        self.pose_idx, self.point_idx = pose_idx, point_idx
        P, M = len(p0), len(X0)
        a, b = gauge
        axis = int(np.argmax(np.abs(p0[b] - p0[a])))
        # column of each of the 6 pose parameters (-1: held fixed), then 3 per point
        col = -np.ones((P, 6), np.int64)
        free = np.ones((P, 6), bool)
        free[a] = False
        free[b, axis] = False
        col[free] = np.arange(int(free.sum()))
        self.pose_col, self.n_pose_params = col, int(free.sum())
        self.point_col = self.n_pose_params + np.arange(3 * M).reshape(M, 3)
        self.n_params = self.n_pose_params + 3 * M
        self.x0 = np.concatenate([np.zeros(self.n_pose_params), X0.ravel()])
        # sparsity pattern: every observation's 2 rows x (6 pose + 3 point) columns
        N = len(pose_idx)
        cols = np.concatenate([col[pose_idx], self.point_col[point_idx]], 1)  # (N, 9)
        self.keep = cols >= 0
        rows = np.repeat(np.arange(2 * N).reshape(N, 2), 9, axis=1).reshape(N, 2, 9)
        self.rows = rows[np.broadcast_to(self.keep[:, None, :], rows.shape)]
        self.cols = np.broadcast_to(cols[:, None, :], rows.shape)[np.broadcast_to(self.keep[:, None, :], rows.shape)]

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        """Positions (P, 3), quaternions (P, 4) and points (M, 3) of parameter vector ``x``."""
        d = np.zeros((len(self.p0), 6))
        m = self.pose_col >= 0
        d[m] = x[self.pose_col[m]]
        p, q = apply_increment(self.p0, self.q0, d)
        X = x[self.n_pose_params:].reshape(-1, 3)
        return p, q, X, d

    def _model(self, x: Array):
        p, q, X, d = self.unpack(x)
        c = self.cam
        i, j = self.pose_idx, self.point_idx
        h, Jp, Jf, z = models.feature_model(p[i], q[i], X[j], c.fx, c.fy, c.cx, c.cy)
        return h, Jp, Jf, z, d

    def residuals(self, x: Array) -> Array:
        """Whitened reprojection errors ``(h - uv) / sigma``, flattened (2N,)."""
        h = self._model(x)[0]
        return ((h - self.uv) * self.w[:, None]).ravel()

    def blocks(self, x: Array) -> tuple[Array, Array, Array]:
        """Whitened residuals (N, 2) and Jacobian blocks: pose increment (N, 2, 6), with
        zeros in held-fixed columns, and point (N, 2, 3)."""
        h, Jp, Jf, _, d = self._model(x)
        i = self.pose_idx
        dq = quat_left_matrix(self.q0) @ exp_jacobian(d[:, 3:])  # dq/dphi = L(q0) dExp/dphi, (P, 4, 3)
        w = self.w[:, None, None]
        Jc = np.concatenate([Jp[:, :, :3], Jp[:, :, 3:] @ dq[i]], 2) * w
        Jc *= self.keep[:, None, :6]
        return (h - self.uv) * self.w[:, None], Jc, Jf * w

    def jacobian(self, x: Array) -> sp.csr_matrix:
        """Analytic Jacobian of :meth:`residuals` (2N, n_params), sparse."""
        _, Jc, Jx = self.blocks(x)
        J = np.concatenate([Jc, Jx], 2)  # (N, 2, 9)
        i = self.pose_idx
        data = J[np.broadcast_to(self.keep[:, None, :], J.shape)]
        return sp.csr_matrix((data, (self.rows, self.cols)), shape=(2 * len(i), self.n_params))

    def rms_px(self, x: Array) -> float:
        h = self._model(x)[0]
        return float(np.sqrt(np.mean(np.sum((h - self.uv) ** 2, 1)))) if len(h) else 0.0


def _robust_cost(r: Array, k: float) -> tuple[float, Array]:
    """Huber cost ``sum rho(|r_i|^2)`` of whitened 2-vectors ``r`` (N, 2) and IRLS weights (N,)."""
    n = np.linalg.norm(r, axis=1)
    inl = n <= k
    rho = np.where(inl, n**2, 2.0 * k * n - k**2)
    return 0.5 * float(rho.sum()), np.where(inl, 1.0, k / np.maximum(n, 1e-300))


def solve_schur_lm(prob: _Problem, k: float, max_iter: int, ftol: float) -> tuple[Array, int, bool, str]:
    """Levenberg-Marquardt with the Schur complement on the points (SBA's algorithm).

    Huber loss by iteratively reweighted least squares (weights per observation). Each
    iteration eliminates the 3x3 point blocks, solves the reduced camera system
    ``(6 P_free)^2`` densely and back-substitutes the points.

    Returns
    -------
    x : solution; iterations : accepted + rejected steps; converged : bool; message : str.
    """
    x = prob.x0.copy()
    P, M = len(prob.p0), (prob.n_params - prob.n_pose_params) // 3
    i, j = prob.pose_idx, prob.point_idx
    free = prob.pose_col >= 0
    r, Jc, Jx = prob.blocks(x)
    cost, wts = _robust_cost(r, k)
    lam, it = 1e-4, 0
    rows = (6 * i[:, None] + np.arange(6)).repeat(3, 1)
    cols = (3 * j[:, None] + np.arange(3))[:, None, :].repeat(6, 1).reshape(len(i), 18)
    while it < max_iter:
        w = wts[:, None, None]
        JcT, JxT = np.swapaxes(Jc, 1, 2), np.swapaxes(Jx, 1, 2)
        U = np.zeros((P, 6, 6))
        np.add.at(U, i, JcT @ (w * Jc))
        V = np.zeros((M, 3, 3))
        np.add.at(V, j, JxT @ (w * Jx))
        Wb = JcT @ (w * Jx)  # (N, 6, 3)
        gc = np.zeros((P, 6))
        np.add.at(gc, i, np.einsum("nab,nb->na", JcT, wts[:, None] * r))
        gx = np.zeros((M, 3))
        np.add.at(gx, j, np.einsum("nab,nb->na", JxT, wts[:, None] * r))
        Wm = sp.csr_matrix((Wb.reshape(len(i), 18).ravel(), (rows.reshape(len(i), 18).ravel(), cols.ravel())),
                           shape=(6 * P, 3 * M))
        while True:
            it += 1
            Ud = U + lam * (U * np.eye(6)) + 1e-12 * np.eye(6)
            Vinv = np.linalg.inv(V + lam * (V * np.eye(3)) + 1e-12 * np.eye(3))
            Vi = sp.bsr_matrix((Vinv, np.arange(M), np.arange(M + 1)), shape=(3 * M, 3 * M)).tocsr()
            WV = Wm @ Vi
            S = -(WV @ Wm.T).toarray()
            for a in range(P):
                S[6 * a:6 * a + 6, 6 * a:6 * a + 6] += Ud[a]
            b = -(gc.ravel() - WV @ gx.ravel())
            f = free.ravel()
            dc = np.zeros(6 * P)
            dc[f] = np.linalg.solve(S[np.ix_(f, f)], b[f])
            dX = -np.einsum("mab,mb->ma", Vinv, gx + (Wm.T @ dc).reshape(M, 3))
            xn = x.copy()
            xn[prob.pose_col[free]] += dc[f]
            xn[prob.n_pose_params:] += dX.ravel()
            rn, Jcn, Jxn = prob.blocks(xn)
            cn, wn = _robust_cost(rn, k)
            if np.isfinite(cn) and cn < cost:
                done = (cost - cn) <= ftol * cost or cn < 1e-20 * len(rn)
                x, r, Jc, Jx, cost, wts = xn, rn, Jcn, Jxn, cn, wn
                lam = max(lam / 3.0, 1e-9)
                if done:
                    return x, it, True, "relative cost decrease below ftol"
                break
            lam *= 5.0
            if lam > 1e8 or it >= max_iter:
                return x, it, lam > 1e8, "no decrease (damping at its limit)" if lam > 1e8 else "iteration limit"
    return x, it, False, "iteration limit"


def triangulate_tracks(camera: PinholeCamera, positions: Array, quats: Array, pose_idx: IntArray,
                       track_idx: IntArray, uv: Array, min_parallax_deg: float) -> tuple[Array, NDArray[np.bool_]]:
    """Triangulate every track from its first and last view.

    Parameters
    ----------
    positions, quats : (P, 3), (P, 4) pose estimates.
    pose_idx, track_idx : (N,) int64 indices of each observation's pose and track
        (tracks numbered 0..M-1, poses in frame order).
    uv : (N, 2) undistorted pixels.

    Returns
    -------
    X : (M, 3) points (zeros where not triangulated); ok : (M,) bool.
    """
    M = int(track_idx.max()) + 1 if len(track_idx) else 0
    order = np.lexsort((pose_idx, track_idx))
    t_sorted = track_idx[order]
    first = order[np.searchsorted(t_sorted, np.arange(M), "left")]
    last = order[np.searchsorted(t_sorted, np.arange(M), "right") - 1]
    X, ok = np.zeros((M, 3)), np.zeros(M, bool)
    pa, pb = pose_idx[first], pose_idx[last]
    pairs = np.unique(np.stack([pa, pb], 1), axis=0)
    for a, b in pairs:
        if a == b:
            continue
        sel = np.flatnonzero((pa == a) & (pb == b))
        Xs, par, good = triangulate(positions[a], quats[a], uv[first[sel]], positions[b], quats[b],
                                    uv[last[sel]], camera)
        X[sel] = Xs
        ok[sel] = good & (par >= min_parallax_deg)
    return X, ok


def bundle_adjust(camera: PinholeCamera, frame_ids, positions: Array, quats: Array, obs: Observations,
                  config: BAConfig | None = None, gauge: tuple[int, int] = (0, 1)) -> BAResult:
    """Triangulate every track seen from two or more poses and adjust everything.

    Parameters
    ----------
    camera : PinholeCamera (undistorted pixels).
    frame_ids : (P,) frame ids of the poses, in the order of ``positions``.
    positions, quats : (P, 3), (P, 4) initial estimate (``q_wc``).
    obs : Observations of tracks in these (and possibly other) frames; observations of
        frames not in ``frame_ids`` are ignored.
    config : BAConfig
    gauge : indices (into ``frame_ids``) of the pose held fixed and of the pose whose
        distance to it is kept.

    Returns
    -------
    BAResult

    Raises
    ------
    EstimatorError
        Fewer than two poses, non-finite input, or no track seen from two poses.
    """
    cfg = config or BAConfig()
    t0 = time.perf_counter()
    fids = np.asarray(frame_ids, np.int64)
    p0 = np.asarray(positions, float).reshape(-1, 3)
    q0 = quat_normalize(np.asarray(quats, float).reshape(-1, 4))
    if len(fids) < 2 or len(p0) != len(fids) or len(q0) != len(fids):
        raise EstimatorError("bundle adjustment needs two or more poses with matching ids")
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(q0))):
        raise EstimatorError("bundle adjustment: initial poses are not finite")
    a, b = gauge
    if a == b or not (0 <= a < len(fids) and 0 <= b < len(fids)):
        raise EstimatorError(f"bad gauge pair {gauge}")
    d_ab = float(np.linalg.norm(p0[b] - p0[a]))
    if not d_ab > 0:
        raise EstimatorError("bundle adjustment: the two gauge poses coincide")
    # observations of posed frames, tracks renumbered
    pos_of = {int(f): k for k, f in enumerate(fids)}
    keep = np.isin(obs.frame, fids)
    pose_idx = np.array([pos_of[int(f)] for f in obs.frame[keep]], np.int64)
    tracks, track_idx = np.unique(obs.track[keep], return_inverse=True)
    uv, sig = obs.uv[keep], obs.sigma_px[keep]
    X, ok = triangulate_tracks(camera, p0, q0, pose_idx, track_idx, uv, cfg.min_parallax_deg)
    sel = ok[track_idx]
    # leave out gross outliers at the initial estimate, then tracks left with < 2 views
    h, _, _, z = models.feature_model(p0[pose_idx], q0[pose_idx], X[track_idx], camera.fx, camera.fy,
                                      camera.cx, camera.cy)
    sel &= (z > 1e-6) & (np.linalg.norm(h - uv, axis=1) <= cfg.max_initial_px)
    views = np.bincount(track_idx[sel], minlength=len(tracks))
    sel &= views[track_idx] >= 2
    used, point_idx = np.unique(track_idx[sel], return_inverse=True)
    if len(used) == 0:
        raise EstimatorError("bundle adjustment: no track is seen from two posed frames with parallax")
    prob = _Problem(camera, p0, q0, X[used], pose_idx[sel], point_idx.astype(np.int64), uv[sel], sig[sel], (a, b))
    rms0 = prob.rms_px(prob.x0)
    k = cfg.robust_px / float(np.median(sig[sel]))
    if cfg.solver == "trf":
        sol = least_squares(prob.residuals, prob.x0, jac=prob.jacobian, method="trf", x_scale="jac",
                            loss=cfg.loss, f_scale=k, max_nfev=cfg.max_nfev, ftol=cfg.ftol, xtol=cfg.xtol,
                            gtol=cfg.gtol, tr_solver="lsmr")
        xs, nit, success, msg = sol.x, int(sol.nfev), bool(sol.success), str(sol.message)
    else:
        xs, nit, success, msg = solve_schur_lm(prob, k, cfg.max_nfev, cfg.ftol)
    p, q, Xo, _ = prob.unpack(xs)
    rms1 = prob.rms_px(xs)
    s = d_ab / float(np.linalg.norm(p[b] - p[a]))  # similarity about pose a: keep |p_b - p_a|
    p, Xo = p[a] + s * (p - p[a]), p[a] + s * (Xo - p[a])
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(Xo))):
        raise EstimatorError("bundle adjustment produced non-finite values")
    return BAResult(fids, p, quat_normalize(q), tracks[used].astype(np.int64), Xo, int(sel.sum()), nit,
                    time.perf_counter() - t0, rms0, rms1, success, msg)


# -- observations from a front end (duck-typed: no front-end import) ----------------------------
def observations_from_frontend(frontend, frame_ids, sigma_px: float = 1.0) -> Observations:
    """Every keypoint with a track id in the given frames of a front end.

    ``frontend.frame(fid)`` must return an object with ``track_ids (N,)`` and ``uv (N, 2)``
    (:class:`~eifslam.frontend.results.FrameFeatures`).
    """
    fr, tr, uv = [], [], []
    for fid in frame_ids:
        ff = frontend.frame(int(fid))
        fr.append(np.full(len(ff.track_ids), int(fid), np.int64))
        tr.append(np.asarray(ff.track_ids, np.int64))
        uv.append(np.asarray(ff.uv, float).reshape(-1, 2))
    if not fr:
        return Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
    f = np.concatenate(fr)
    return Observations(f, np.concatenate(tr), np.concatenate(uv), np.full(len(f), float(sigma_px)))


__all__ = ["BAConfig", "BAResult", "Observations", "bundle_adjust",
           "observations_from_frontend", "triangulate_tracks", "exp_jacobian", "apply_increment"]
