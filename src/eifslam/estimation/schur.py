"""The active window's pose Schur complement by blocks of its staircase (pure NumPy/SciPy).

The window solve (:meth:`~eifslam.estimation.window.ActiveWindow.solve`) needs
``S = P - W^T W`` with ``W = L^-1 B`` (``D_f = L_f L_f^T`` per feature): ``B`` is
``3 f x 7 p`` and dense in memory, but a feature is coupled only to the poses that
observed it while it was active. With the poses in the order they entered the state
that is a staircase: a feature seen from pose ``a`` on has its columns in ``[a, p)``
(tracked until now) or in ``[a, b]``. On the loop world the window holds about 1,200
features and 60-110 poses, a feature is coupled to 5 poses in the median, and the dense
``W^T W`` (``3 f (7 p)^2 / 2`` multiply-adds) was most of the per-frame recovery.

:func:`subtract_gram` sorts the features by their first pose, groups those with the same
first pose, and joins neighbouring groups into chunks chosen by dynamic programming on a
cost model (multiply-adds of each chunk's ``dsyrk`` over its column span, plus the
update of that span of ``S`` and a fixed cost per chunk): each chunk adds its
``W_c^T W_c`` into the span it covers. The result is the same lower triangle as the dense
product (every nonzero of ``W`` lies in its chunk's span), up to rounding.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.blas import dsyrk

from .state import POSE_DIM

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["coupled_poses", "staircase_chunks", "subtract_gram"]

#: Cost model of one chunk, in nanoseconds: per multiply-add of its dsyrk, per entry of
#: the span of ``S`` it updates, and per chunk (Python and the gather). Only the
#: partition depends on it, never the result.
_NS_PER_MAC, _NS_PER_ENTRY, _NS_PER_CHUNK = 0.1, 1.5, 20_000.0


def staircase_chunks(coupled: NDArray[np.bool_]) -> list[tuple[IntArray, int, int]]:
    """Partition the features into chunks of nearby first poses.

    Parameters
    ----------
    coupled : (F, p) bool
        Whether feature ``f`` is coupled to window pose ``j`` (poses in state order).

    Returns
    -------
    list of (rows, lo, hi)
        ``rows`` (n,) int: features of the chunk; ``[lo, hi)``: the poses its features
        are coupled to lie in this range. Features coupled to no pose are in no chunk.
    """
    F, p = coupled.shape
    if F == 0 or p == 0:
        return []
    any_ = coupled.any(axis=1)
    first = np.argmax(coupled, axis=1)
    last = p - 1 - np.argmax(coupled[:, ::-1], axis=1)
    rows = np.flatnonzero(any_)
    if not len(rows):
        return []
    order = rows[np.argsort(first[rows], kind="stable")]
    fs = first[order]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(fs)) + 1])
    ends = np.concatenate([starts[1:], [len(order)]])
    g_first = fs[starts]
    g_last = np.maximum.reduceat(last[order], starts)
    g_n = ends - starts
    G = len(starts)
    cum_n = np.concatenate([[0], np.cumsum(g_n)])
    best = np.zeros(G + 1)
    arg = np.zeros(G + 1, np.int64)
    for j in range(G):  # best[j + 1]: groups 0..j, the last chunk groups i..j
        i = np.arange(j + 1)
        hi = np.maximum.accumulate(g_last[j::-1])[::-1] + 1  # max last over groups i..j
        u = POSE_DIM * (hi - g_first[i]).astype(float)
        n = (cum_n[j + 1] - cum_n[i]).astype(float)
        cost = best[i] + _NS_PER_MAC * 1.5 * n * u * u + _NS_PER_ENTRY * u * u + _NS_PER_CHUNK
        k = int(np.argmin(cost))
        best[j + 1], arg[j + 1] = cost[k], k
    chunks = []
    j = G
    while j > 0:
        i = int(arg[j])
        lo = int(g_first[i])
        hi = int(g_last[i:j].max()) + 1
        chunks.append((order[cum_n[i]:cum_n[j]], lo, hi))
        j = i
    return chunks[::-1]


def coupled_poses(B: Array, n_poses: int) -> NDArray[np.bool_]:
    """Which window poses each feature is coupled to.

    Parameters
    ----------
    B : (3 F, 7 p) float
        Feature-pose coupling, three rows per feature, seven columns per pose.
    n_poses : int
        ``p``.

    Returns
    -------
    (F, p) bool
        Whether any of the 21 entries of a feature-pose block is nonzero.
    """
    F = B.shape[0] // 3
    nz = (B != 0).reshape(F, 3, -1)
    rows = (nz[:, 0] | nz[:, 1] | nz[:, 2]).reshape(F, n_poses, POSE_DIM)
    out = rows[:, :, 0].copy()
    for j in range(1, POSE_DIM):  # ORs of strided slices: faster than any() over 7
        out |= rows[:, :, j]
    return out


def subtract_gram(S: Array, W: Array, coupled: NDArray[np.bool_], lower: bool = True) -> Array:
    """``S - W^T W`` by chunks of the staircase.

    Parameters
    ----------
    S : (7 p, 7 p) float
        Modified in place. With ``lower`` only on and below the diagonal (the entries
        above it are left as they are, as ``dsyrk`` with ``lower=1`` leaves them), else
        both triangles.
    W : (3 F, 7 p) float
        Three rows per feature; its nonzeros lie in the poses ``coupled`` marks.
    coupled : (F, p) bool
        See :func:`staircase_chunks`.
    lower : bool

    Returns
    -------
    S
    """
    F = len(coupled)
    W3 = W.reshape(F, 3, -1)
    for rows, lo, hi in staircase_chunks(coupled):
        a, b = POSE_DIM * lo, POSE_DIM * hi
        sub = W3[rows, :, a:b].reshape(3 * len(rows), b - a)
        G = dsyrk(1.0, sub.T, trans=0, lower=1) if lower else sub.T @ sub
        S[a:b, a:b] -= G
    return S
