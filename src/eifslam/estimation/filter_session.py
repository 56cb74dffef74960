"""Sessions of the information filter: what :class:`~eifslam.estimation.filter.InformationFilter`
saves and restores (arrays and JSON values, :mod:`.statedict`), as a mixin of that class
(its own attributes; kept apart so that the filter module stays about filtering)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import EstimatorError, SessionError
from .measurements import pack_features, pack_relative, unpack_features, unpack_relative
from .state import FEATURE_DIM, POSE_DIM, StateKind
from .statedict import check_index, sub, take, take_float, take_ids, take_int

__all__ = ["FilterSessionMixin"]


class FilterSessionMixin:
    """``state_dict``/``load_state_dict`` of :class:`~eifslam.estimation.filter.InformationFilter`."""

    # -- sessions -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps, as arrays and JSON values (:mod:`.statedict`): the layout,
        the complete estimate, ``I`` (CSC arrays) and ``i``, the priors, every stored
        measurement and the incremental recovery's bookkeeping. The filter is not changed."""
        order = self.layout.order
        x = self.x.copy()
        if self.incremental is not None and self.incremental.valid:
            self.incremental.full_solution(x)
        I = sp.csc_matrix(self.information_matrix(), copy=True)
        I.sum_duplicates()
        weak = {kind: [(i, v) for (kd, i), v in self.priors.weak.items() if kd == kind] for kind in StateKind}
        batches = self.store.features
        return {
            "is_feature": np.array([k.kind == StateKind.FEATURE for k in order], bool),
            "id": np.array([k.id for k in order], np.int64),
            "x": x,
            "x_first": self.first_estimates.copy(),
            "I": {"data": I.data.astype(float), "indices": I.indices.astype(np.int64),
                  "indptr": I.indptr.astype(np.int64)},
            "i": self.information_vector(),
            "prior_pose": {"ids": np.array(list(self.priors.pose), np.int64),
                           "p": np.array([p for p, _ in self.priors.pose.values()], float).reshape(-1, 3),
                           "q": np.array([q for _, q in self.priors.pose.values()], float).reshape(-1, 4)},
            "scale": None if self.priors.scale is None else list(self.priors.scale),
            **{f"weak_{kind.value}": {"ids": np.array([i for i, _ in weak[kind]], np.int64),
                                      "x": np.array([v for _, v in weak[kind]], float).reshape(-1, n)}
               for kind, n in ((StateKind.POSE, POSE_DIM), (StateKind.FEATURE, FEATURE_DIM))},
            "zm": pack_features(self.store.all_features()),
            "zm_batches": np.array([len(b) for b in batches], np.int64),
            "relative": pack_relative(self.store.relative),
            "incremental": None if self.incremental is None else self.incremental.state_dict(),
            "online": None if self.online is None else self.online.state_dict(),
        }

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict` into this (new, empty) filter. The incremental
        recovery's window starts invalid and is rebuilt from ``I`` at the next step.

        Raises
        ------
        SessionError
            On a missing, malformed or inconsistent entry (nothing is trusted).
        """
        if self.layout.n_states:
            raise SessionError("a session loads into a new filter only")
        isf = take(d, "is_feature", bool, (None,))
        ids = take_ids(d, "id", len(isf))
        try:
            for f, i in zip(isf.tolist(), ids.tolist()):
                (self.layout.add_feature if f else self.layout.add_pose)(i)
        except EstimatorError as exc:
            raise SessionError(f"bad state layout: {exc}") from None
        n = self.dim
        self._grow()
        Id = sub(d, "I")
        indptr = take_ids(Id, "indptr", n + 1)
        data = take(Id, "data", np.float64, (None,))
        indices = take_ids(Id, "indices", len(data))
        if indptr[0] != 0 or indptr[-1] != len(data) or np.any(np.diff(indptr) < 0):
            raise SessionError("array 'indptr' is not a CSC column pointer")
        check_index(indices, n, "array 'indices'")
        self.info.set(sp.csc_matrix((data, indices, indptr), shape=(n, n)), take(d, "i", np.float64, (n,)))
        self._x[:n] = take(d, "x", np.float64, (n,))
        self._xfe[:n] = take(d, "x_first", np.float64, (n,)) if "x_first" in d else self._x[:n]
        pp = sub(d, "prior_pose")
        pids = take_ids(pp, "ids")
        self._check_states(StateKind.POSE, pids, "prior_pose")
        for fid, p, q in zip(pids.tolist(), take(pp, "p", np.float64, (len(pids), 3)),
                             take(pp, "q", np.float64, (len(pids), 4))):
            self.priors.pose[fid] = (p.copy(), q.copy())
        sc = d.get("scale")
        if sc is not None:
            if not (isinstance(sc, list) and len(sc) == 3):
                raise SessionError("entry 'scale' must be [frame_a, frame_b, distance]")
            sd = dict(zip("abd", sc))
            a, b, dist = take_int(sd, "a", 0), take_int(sd, "b", 0), take_float(sd, "d")
            self._check_states(StateKind.POSE, np.array([a, b]), "scale")
            self.priors.scale = (a, b, dist)
        for kind, size in ((StateKind.POSE, POSE_DIM), (StateKind.FEATURE, FEATURE_DIM)):
            w = sub(d, f"weak_{kind.value}")
            wids = take_ids(w, "ids")
            self._check_states(kind, wids, f"weak_{kind.value}")
            for i, v in zip(wids.tolist(), take(w, "x", np.float64, (len(wids), size))):
                self.priors.weak[(kind, i)] = v.copy()
        obs = unpack_features(sub(d, "zm"))
        self._check_states(StateKind.POSE, obs.pose, "zm")
        self._check_states(StateKind.FEATURE, obs.feature, "zm")
        sizes = take_ids(d, "zm_batches")
        if int(sizes.sum()) != len(obs):
            raise SessionError("array 'zm_batches' does not add up to the stored Zm")
        bounds = np.cumsum(sizes)
        self.store.features = [obs.subset(slice(a, b)) for a, b in zip(bounds - sizes, bounds)]
        self.store.relative = unpack_relative(sub(d, "relative"))
        self._check_states(StateKind.POSE, np.array([[r.i, r.j] for r in self.store.relative], np.int64), "relative")
        inc = d.get("incremental")
        if (inc is None) != (self.incremental is None):
            raise SessionError("entry 'incremental' does not match the configured recovery")
        if self.incremental is not None:
            self.incremental.load_state_dict(inc, n)
        if self.online is not None and d.get("online") is not None:  # after info.set, which clears it
            self.online.load_state_dict(sub(d, "online"), n)
        self._factor = None

