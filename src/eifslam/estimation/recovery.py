"""State recovery ``I x = i`` (paper eq. 9) and marginal covariances (pure NumPy / SciPy).

The information matrix of this problem has a special structure that the solver uses:
no measurement involves two features, so the feature-feature part ``I_ff`` is block
diagonal with 3x3 blocks. Eliminating the features first (the Schur complement onto the
poses, the "reduced camera system" of bundle adjustment) leaves a small sparse system
``S = I_pp - I_pf I_ff^-1 I_fp`` of dimension ``7 x poses``, factorised by sparse
Cholesky with a fill-reducing (minimum degree) ordering; the features are then
back-substituted block by block. This is an exact Cholesky factorisation of ``I`` in the
elimination order "features first, then poses".

Marginal covariances come from the same factorisation without any dense inverse:
a pose block of ``I^-1`` equals the block of ``S^-1`` (7 sparse solves); a feature block
is ``D^-1 + D^-1 B S^-1 B^T D^-1`` with ``D`` its 3x3 information block and ``B`` its
coupling to the poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import splu

from ..errors import EstimatorError
from .information import SummedRows, block
from .blocks import apply_blocks, block_diagonal_csr, cholesky_blocks, gather_diagonal_blocks, inverse_spd_blocks

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def sparse_cholesky(A: sp.spmatrix):
    """Factorise a symmetric positive definite sparse matrix.

    SciPy has no sparse Cholesky; SuperLU with a symmetric minimum-degree ordering on
    ``A + A^T`` and no pivoting off the diagonal is the same factorisation (``L U`` with
    ``U = D L^T``). Returns an object with ``solve(b)``.
    """
    A = sp.csc_matrix(A)
    try:
        return splu(
            A,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options=dict(SymmetricMode=True),
        )
    except RuntimeError as exc:  # exactly singular
        raise EstimatorError(f"information matrix is singular ({exc}); is the gauge fixed?") from exc


@dataclass
class SchurFactor:
    """Factorisation of ``I`` by eliminating features then poses.

    Attributes
    ----------
    pose_idx : (P*7,) int   state indices of the poses, in state order.
    feat_idx : (F*3,) int   state indices of the features, in state order.
    Dinv : (F, 3, 3)        inverses of the feature information blocks.
    B : csr (F*3, P*7) or (F*3, N)
        ``I_fp``; with ``B_cols``, a wider matrix whose columns ``B_cols`` are the poses'
        (the others are ignored).
    S_factor                factorisation of the reduced pose system.
    B_cols : (P*7,) int or None
        Positions of the poses among ``B``'s columns, None when they are all of them. A
        rebuild's factor shares the coupling kept by
        :class:`~eifslam.estimation.elimination.FeatureElimination` this way instead of
        a copy of its columns (on the loop world 10 M non-zeros, 120 MB).
    """

    pose_idx: IntArray
    feat_idx: IntArray
    Dinv: Array
    B: sp.csr_matrix
    S_factor: object
    n: int
    B_cols: IntArray | None = None

    def B_times(self, xp: Array, rows: IntArray | None = None) -> Array:
        """``I_fp xp`` for pose values ``xp (P*7,)`` (or ``(P*7, m)``); only its rows
        ``rows`` (reading only those rows of ``B``) when given."""
        B = self.B if rows is None else self.B[rows]
        if self.B_cols is None:
            return np.asarray(B @ xp)
        full = np.zeros((self.B.shape[1],) + np.shape(xp)[1:])
        full[self.B_cols] = xp
        return np.asarray(B @ full)

    def BT_times(self, v: Array | sp.spmatrix) -> Array | sp.spmatrix:
        """``I_pf v`` for ``v (F*3,)``, ``(F*3, m)`` or sparse ``(F*3, m)``: shape ``(P*7, ...)``."""
        out = self.B.T @ v
        if self.B_cols is None:
            return out
        return sp.csr_matrix(out)[self.B_cols] if sp.issparse(out) else out[self.B_cols]

    def apply_dinv(self, v: Array) -> Array:
        """Apply the block-diagonal ``I_ff^-1`` to ``(F*3,)`` or ``(F*3, m)``."""
        return apply_blocks(self.Dinv, v)

    def solve(self, b: Array) -> Array:
        """Solve ``I x = b`` for ``b`` of shape ``(n,)`` or ``(n, m)``."""
        b = np.asarray(b, dtype=float)
        bp, bf = b[self.pose_idx], b[self.feat_idx]
        Dbf = self.apply_dinv(bf)
        rhs = bp - self.BT_times(Dbf)
        xp = self.S_factor.solve(rhs) if len(self.pose_idx) else rhs
        xf = Dbf - self.apply_dinv(self.B_times(xp))
        x = np.zeros_like(b)
        x[self.pose_idx] = xp
        x[self.feat_idx] = xf
        return x

    def solve_entries(self, r: Array, idx: IntArray) -> Array:
        """Solve with a right side ``r (len(idx),)`` given on state entries ``idx`` (the
        factorised ones, in any order); the solution on the same entries."""
        b = np.zeros(self.n)
        b[idx] = r
        return self.solve(b)[idx]

    def project(self, C: sp.spmatrix, b: Array) -> tuple[Array, Array]:
        """``C^T A^-1 C (k, k)`` and ``C^T A^-1 b (k,)`` for the factorised ``A``.

        ``C (n, k)`` is sparse (rows on the state; rows outside the factorised entries
        are ignored) and ``b (n,)``. Uses the elimination order, features first: with
        ``R = C_p - B^T D^-1 C_f``, ``C^T A^-1 C = C_f^T D^-1 C_f + R^T S^-1 R``, so only
        the rows of ``B`` that ``C_f`` touches are read and ``S`` is solved for ``k + 1``
        right sides (a rebuild's Schur complement onto the active window without the
        ``n x k`` dense solve).
        """
        C = sp.csr_matrix(C)
        k = C.shape[1]
        Cf, Cp = C[self.feat_idx], C[self.pose_idx]
        Dsp = block_diagonal_csr(self.Dinv)
        DCf = sp.csr_matrix(Dsp @ Cf)
        Dbf = self.apply_dinv(np.asarray(b, float)[self.feat_idx])
        Rt = (sp.csr_matrix(Cp.T) - sp.csr_matrix(self.BT_times(DCf)).T).toarray()  # (k, 7P)
        rb = np.asarray(b, float)[self.pose_idx] - self.BT_times(Dbf)
        if len(self.pose_idx):
            Y = self.S_factor.solve(np.ascontiguousarray(np.column_stack([Rt.T, rb])))
        else:
            Y = np.zeros((0, k + 1))
        CtAC = (Cf.T @ DCf).toarray() + Rt @ Y[:, :k]
        CtAb = Cf.T @ Dbf + Rt @ Y[:, k]
        return 0.5 * (CtAC + CtAC.T), np.asarray(CtAb).ravel()

    def restricted(self, idx: IntArray) -> "RestrictedSolve":
        """A solver of the factorised block that takes and returns vectors on ``idx``."""
        return RestrictedSolve(self, np.asarray(idx, np.int64))

    def covariance(self, idx: IntArray) -> Array:
        """The block of ``I^-1`` on state indices ``idx`` (k,), without a full inverse."""
        idx = np.asarray(idx, dtype=np.int64)
        E = np.zeros((self.n, len(idx)))
        E[idx, np.arange(len(idx))] = 1.0
        X = self.solve(E)
        C = X[idx]
        return 0.5 * (C + C.T)


@dataclass
class RestrictedSolve:
    """``solve(r)`` of a :class:`SchurFactor` with vectors on state entries ``idx``."""

    factor: SchurFactor
    idx: IntArray

    def solve(self, r: Array) -> Array:
        """``A^-1 r`` for ``r (len(idx),)``, on the same entries."""
        return self.factor.solve_entries(r, self.idx)

    def sparse(self, rows: IntArray) -> "SparseSolve":
        """A solver for right sides that are zero outside positions ``rows`` of ``idx``."""
        return SparseSolve(self, np.asarray(rows, np.int64))


class SparseSolve:
    """``A^-1 r`` on the entries of a :class:`RestrictedSolve` for right sides ``r`` that
    are zero outside a fixed set of positions ``rows`` (a rebuild's conditional, whose
    coupling to the active window touches few of its entries): with ``r_f``, ``r_p`` the
    feature and pose parts, ``x_p = S^-1 (r_p - B_c^T D_c^-1 r_c)`` reads only the rows
    ``B_c`` of the features ``r`` touches, and ``x_f = D^-1 (r_f - B x_p)``. The same
    solution as :meth:`RestrictedSolve.solve` up to rounding, without its product with
    every row of ``B`` and its pass over every feature block for the right side.

    Parameters
    ----------
    restricted : RestrictedSolve
    rows : (k,) int
        Positions in ``restricted.idx`` where right sides may be non-zero.
    """

    def __init__(self, restricted: RestrictedSolve, rows: IntArray) -> None:
        f = restricted.factor
        self.factor = f
        n = f.n
        fpos = np.full(n, -1, np.int64)
        fpos[f.feat_idx] = np.arange(len(f.feat_idx))
        ppos = np.full(n, -1, np.int64)
        ppos[f.pose_idx] = np.arange(len(f.pose_idx))
        # where the factor's solution (pose then feature entries) lands in restricted.idx
        self._out_p = ppos[restricted.idx]
        self._out_f = fpos[restricted.idx]
        ent = restricted.idx[rows]
        self._rp, self._rf = ppos[ent] >= 0, fpos[ent] >= 0
        self._ppos = ppos[ent][self._rp]
        feats, inv = np.unique(fpos[ent][self._rf] // 3, return_inverse=True)
        self._frow = (3 * inv + fpos[ent][self._rf] % 3).astype(np.int64)  # into the touched blocks' rows
        self._fent = (3 * feats[:, None] + np.arange(3)).ravel()  # their rows of B
        self._Dinv_c = f.Dinv[feats]
        Bc = f.B[self._fent]
        self._Bc_T = sp.csr_matrix((Bc if f.B_cols is None else Bc[:, f.B_cols]).T) if len(feats) else None

    def solve(self, r: Array, at: IntArray | None = None) -> Array:
        """``A^-1 r``: ``r (k,)`` the right side at ``rows``; the solution on every entry
        of the restricted solve (its ``idx`` order), or on its positions ``at`` only: then
        only the rows of ``B`` of the features there are read (the pose system is solved
        whole either way)."""
        f = self.factor
        rhs = np.zeros(len(f.pose_idx))
        rhs[self._ppos] = r[self._rp]
        Dbc = np.zeros(0)
        if self._Bc_T is not None:
            bc = np.zeros(len(self._fent))
            bc[self._frow] = r[self._rf]
            Dbc = apply_blocks(self._Dinv_c, bc)
            rhs -= self._Bc_T @ Dbc
        xp = f.S_factor.solve(rhs) if len(f.pose_idx) else rhs
        out_p, out_f = (self._out_p, self._out_f) if at is None else (self._out_p[at], self._out_f[at])
        isp = out_p >= 0
        if at is None:
            xf = -f.apply_dinv(f.B_times(xp))
        else:  # the feature rows asked for; the others are left at zero and not read
            blocks = np.unique(out_f[~isp] // 3)
            rows = (3 * blocks[:, None] + np.arange(3)).ravel()
            xf = np.zeros(len(f.feat_idx))
            xf[rows] = -apply_blocks(f.Dinv[blocks], f.B_times(xp, rows))
        if len(Dbc):
            xf[self._fent] += Dbc
        out = np.empty(len(out_p))
        out[isp] = xp[out_p[isp]]
        out[~isp] = xf[out_f[~isp]]
        return out


def feature_blocks(I: sp.csr_matrix | SummedRows, feat_idx: IntArray, pose_idx: IntArray) -> tuple[Array, sp.csr_matrix]:
    """The features' 3x3 information blocks and their coupling to the poses, read from the
    features' rows of ``I`` in one pass (no column fancy-indexing of the sparse matrix).

    Parameters
    ----------
    I : (n, n) CSR, or :class:`~eifslam.estimation.information.SummedRows` (only rows are read)
    feat_idx : (3 F,) int
        State indices of the features, three per feature.
    pose_idx : (7 P,) int
        State indices of the poses.

    Returns
    -------
    D : (F, 3, 3)
        ``I_ff`` blocks.
    B : (3 F, 7 P) CSR
        ``I_fp``, columns in the order of ``pose_idx``.

    Raises
    ------
    EstimatorError
        When two features share a measurement (``I_ff`` is not block diagonal).
    """
    n = I.shape[0]
    F = len(feat_idx) // 3
    If = I[feat_idx]
    If.sum_duplicates()
    row = np.repeat(np.arange(3 * F), np.diff(If.indptr))
    col, val = If.indices, If.data
    fpos = np.full(n, -1, np.int64)
    fpos[feat_idx] = np.arange(3 * F)
    ppos = np.full(n, -1, np.int64)
    ppos[pose_idx] = np.arange(len(pose_idx))
    fc = fpos[col]
    isf = fc >= 0
    D = gather_diagonal_blocks(row[isf], fc[isf], val[isf], F)
    pc = ppos[col]
    isp = pc >= 0
    counts = np.bincount(row[isp], minlength=3 * F)
    indptr = np.concatenate([[0], np.cumsum(counts)])
    B = sp.csr_matrix((val[isp], pc[isp], indptr), shape=(3 * F, len(pose_idx)))
    B.sort_indices()
    return D, B


def gram_by_blocks(B: sp.csr_matrix, Dinv: Array) -> sp.csr_matrix:
    """``B^T D^-1 B`` (``D^-1`` block diagonal, ``(F, 3, 3)``) as ``W^T W`` with ``W = L^T B``,
    ``D^-1 = L L^T``, in scipy's block sparse format of 3x7 feature-pose blocks: the same
    sums as the CSR product, about three times faster (its inner products are the 7x3
    by 3x7 blocks, not single entries)."""
    F = len(Dinv)
    Bb = sp.bsr_matrix(B, blocksize=(3, 7))
    brow = np.repeat(np.arange(F), np.diff(Bb.indptr))
    Lt = cholesky_blocks(Dinv).transpose(0, 2, 1)
    Wb = sp.bsr_matrix((np.einsum("bij,bjk->bik", Lt[brow], Bb.data), Bb.indices, Bb.indptr), shape=B.shape)
    return (Wb.T @ Wb).tocsr()


def _marginal_by_solves(factor: SchurFactor, I: sp.csr_matrix | SummedRows, keep: IntArray, i: Array
                        ) -> tuple[SchurFactor, Array, Array]:
    """:func:`factorize_onto`'s result from ``len(keep) + 1`` solves with ``factor``
    (:meth:`SchurFactor.project`)."""
    CtAC, CtAb = factor.project(sp.csr_matrix(I[keep].T), i)
    return factor, block(I, keep, keep).toarray() - CtAC, np.asarray(i, float)[keep] - CtAb


def factorize_onto(I: sp.spmatrix, pose_idx: IntArray, feat_idx: IntArray, keep: IntArray,
                   i: Array) -> tuple[SchurFactor, Array, Array]:
    """Factorise the block of ``I`` on ``pose_idx`` and ``feat_idx`` (as :func:`factorize`)
    and eliminate it from the block on ``pose_idx``, ``feat_idx`` and the poses ``keep``:
    the marginal information of ``keep``, ``P = I_kk - I_km I_mm^-1 I_mk`` and
    ``b = i_k - I_km I_mm^-1 i_m`` (``m`` the factorised entries).

    :meth:`SchurFactor.project` gives the same from ``len(keep) + 1`` solves of the pose
    system; here the features are eliminated onto both pose sets at once and the reduced
    matrix, ``keep`` ordered last after the pose system's own fill-reducing order, is
    factorised once more: the trailing block of that ``L U`` is ``P``. On the loop world's
    rebuilds (7,000 factorised pose entries, ~1,000 kept) that is a fraction of the
    solves' time. Falls back to :meth:`SchurFactor.project` if SuperLU reorders the
    columns it was given or meets a zero pivot in the kept block.

    Parameters
    ----------
    I : sparse (n, n)
    pose_idx, feat_idx : int arrays
        The entries eliminated (``m``), poses and features (three per feature).
    keep : (k,) int
        Pose entries kept; disjoint from ``m``; other entries of ``I`` are ignored.
    i : (n,) float
        The information vector.

    Returns
    -------
    factor : SchurFactor
        Of ``I_mm`` (what :func:`factorize` returns).
    P : (k, k) float
    b : (k,) float
    """
    I = sp.csr_matrix(I)
    pose_idx, feat_idx, keep = (np.asarray(a, np.int64) for a in (pose_idx, feat_idx, keep))
    nm, k = len(pose_idx), len(keep)
    if not len(feat_idx) or not nm or not k:
        return _marginal_by_solves(factorize(I, pose_idx, feat_idx), I, keep, i)
    ps = np.concatenate([pose_idx, keep])
    D, B = feature_blocks(I, feat_idx, ps)
    Dinv = inverse_spd_blocks(D)
    i = np.asarray(i, float)
    y = apply_blocks(Dinv, i[feat_idx])
    return reduced_onto(I, pose_idx, feat_idx, keep, i, Dinv, sp.csr_matrix(B[:, :nm]), gram_by_blocks(B, Dinv),
                        B.T @ y)


def reduced_onto(I: sp.csr_matrix | SummedRows, pose_idx: IntArray, feat_idx: IntArray, keep: IntArray, i: Array,
                 Dinv: Array, B: sp.csr_matrix, G: sp.spmatrix, g: Array,
                 B_cols: IntArray | None = None) -> tuple[SchurFactor, Array, Array]:
    """:func:`factorize_onto` from the features' elimination made already (e.g. kept between
    rebuilds, :class:`~eifslam.estimation.elimination.FeatureElimination`).

    Parameters
    ----------
    I, pose_idx, feat_idx, keep, i : as :func:`factorize_onto` (``keep`` non-empty); ``I`` may be a
        :class:`~eifslam.estimation.information.SummedRows` (only rows are read).
    Dinv : (F, 3, 3)
        Inverses of the information blocks of the features ``feat_idx`` (their order).
    B : CSR (3 F, len(pose_idx)), or (3 F, N) with ``B_cols``
        Their coupling to the poses ``pose_idx``.
    G : sparse (len(ps), len(ps)), ``ps = [pose_idx, keep]``
        ``B_ps^T D^-1 B_ps`` with ``B_ps`` their coupling to the poses ``ps``.
    g : (len(ps),)
        ``B_ps^T D^-1 i_f``.
    B_cols : (len(pose_idx),) int, optional
        Positions of ``pose_idx`` among ``B``'s columns when ``B`` is wider (shared by the
        factor, not copied: :attr:`SchurFactor.B_cols`).

    Returns
    -------
    As :func:`factorize_onto`.
    """
    pose_idx, keep = np.asarray(pose_idx, np.int64), np.asarray(keep, np.int64)
    nm, k = len(pose_idx), len(keep)
    ps = np.concatenate([pose_idx, keep])
    i = np.asarray(i, float)
    T = sp.csr_matrix(block(I, ps, ps) - G)
    T = 0.5 * (T + T.T)
    r = i[ps] - np.asarray(g).ravel()
    if nm == 0:  # only features eliminated: the reduced matrix is the marginal
        factor = SchurFactor(pose_idx, np.asarray(feat_idx, np.int64), Dinv, B, None, I.shape[0],
                             B_cols)
        return factor, T.toarray(), r
    factor = SchurFactor(pose_idx, np.asarray(feat_idx, np.int64), Dinv, B, sparse_cholesky(T[:nm][:, :nm]),
                         I.shape[0], B_cols)
    b = r[nm:] - sp.csr_matrix(T[nm:][:, :nm]) @ factor.S_factor.solve(r[:nm])
    order = np.concatenate([np.argsort(factor.S_factor.perm_c), nm + np.arange(k)])
    ident = np.arange(nm + k)
    try:
        lu = splu(sp.csc_matrix(T[order][:, order]), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                  options=dict(SymmetricMode=True))
    except RuntimeError:  # a zero pivot in the kept block (S itself factorised): the solves
        lu = None
    if lu is None or not (np.array_equal(lu.perm_c, ident) and np.array_equal(lu.perm_r, ident)):
        return _marginal_by_solves(factor, I, keep, i)
    L, U = lu.L.tocsc()[:, nm:], lu.U.tocsr()[nm:]  # the trailing blocks' columns of L, rows of U
    P = L[nm:].toarray() @ U[:, nm:].toarray()
    return factor, 0.5 * (P + P.T), np.asarray(b).ravel()


def factorize(I: sp.spmatrix, pose_idx: IntArray, feat_idx: IntArray) -> SchurFactor:
    """Factorise the information matrix ``I`` (n x n) given which entries are features.

    Parameters
    ----------
    I : sparse (n, n) information matrix.
    pose_idx : (P*7,) state indices of poses.
    feat_idx : (F*3,) state indices of features (grouped by three, in feature order).

    The two index sets may cover only part of the state: the factor is then that of the
    block ``I[idx][:, idx]`` (``idx`` their union), still addressed by state index.
    """
    I = sp.csr_matrix(I)
    n = I.shape[0]
    F = len(feat_idx) // 3
    if F:
        D, B = feature_blocks(I, np.asarray(feat_idx, np.int64), np.asarray(pose_idx, np.int64))
        Dinv = inverse_spd_blocks(D)
        S = block(I, pose_idx, pose_idx) - gram_by_blocks(B, Dinv)
    else:
        Dinv = np.zeros((0, 3, 3))
        B = sp.csr_matrix((0, len(pose_idx)))
        S = block(I, pose_idx, pose_idx)
    S = sp.csc_matrix(0.5 * (S + S.T))
    S_factor = sparse_cholesky(S) if len(pose_idx) else None
    return SchurFactor(pose_idx, feat_idx, Dinv, B, S_factor, n)
