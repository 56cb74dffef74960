"""How the filter recovers its state each keyframe: an object the filter is given.

:class:`~eifslam.estimation.filter.InformationFilter` delegates everything that depends on
the way the state is recovered to one of these, chosen at construction:

* :class:`FullRecovery` solves ``I x = i`` over the whole state every time (sparse
  Cholesky with the features eliminated first, :mod:`.recovery`): exact, ``O(n)`` and more
  per keyframe;
* :class:`WindowRecovery` keeps an active window of recently measured states exactly solved
  and the rest marginalised into conditionals (:class:`~.incremental.IncrementalRecovery`,
  paper III-G), optionally with online relinearisation of the window's measurements
  (:class:`~.relinearisation.OnlineRelinearisation`): a cost per keyframe bounded by the
  window, not by the map.

Both answer the same questions (recover, complete or recent estimate, marginal covariances
where cheap, session state), so the filter has no branch on which one it holds.
"""

from __future__ import annotations

import dataclasses
from contextlib import AbstractContextManager, nullcontext
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError, SessionError
from .blocks import block_entries, dense_diagonal_blocks
from .incremental import IncrementalRecovery, RecoveryStats, TrackedInformationStore
from .information import InformationStore
from .relinearisation import OnlineRelinearisation
from .state import POSE_DIM

if TYPE_CHECKING:  # the filter holds these objects; they only call its public methods
    from .filter import InformationFilter

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["RecoveryMode", "FullRecovery", "WindowRecovery"]


@runtime_checkable
class RecoveryMode(Protocol):
    """What :class:`~eifslam.estimation.filter.InformationFilter` asks of its recovery."""

    incremental: IncrementalRecovery | None
    online: OnlineRelinearisation | None

    def information_store(self) -> InformationStore:
        """A new, empty store of ``I`` and ``i``, with this recovery listening to it."""
        ...

    def fresh(self) -> "RecoveryMode":
        """A recovery of the same kind and settings that has seen nothing."""
        ...

    def recover(self, filt: "InformationFilter") -> Array:
        """The per-keyframe recovery into ``filt``'s estimate; returns ``filt.x``."""
        ...

    def recover_rebuilt(self, filt: "InformationFilter") -> Array:
        """A complete recovery after ``I`` was replaced wholesale; returns ``filt.x``."""
        ...

    def complete(self, filt: "InformationFilter", x: Array) -> Array:
        """Bring every state of ``x`` (``filt``'s estimate or a copy) to the solution."""
        ...

    def recent(self, filt: "InformationFilter", steps: int) -> Array:
        """Bring the states of about the last ``steps`` keyframes to the solution."""
        ...

    def measured_within(self, starts: IntArray, steps: int | None) -> NDArray[np.bool_]:
        """Whether the states whose blocks start at ``starts`` were measured in the last
        ``steps`` recoveries (None: recently enough to be in the active window; all True
        where the recovery does not tell)."""
        ...

    def recent_entries(self, steps: int, n: int) -> IntArray | None:
        """Entries, of a state of dimension ``n``, of the states measured in the last
        ``steps`` recoveries (their block starts among them), without a pass over every
        state's block (None: the recovery does not tell, every state counts)."""
        ...

    def affordable(self, starts: IntArray) -> bool:
        """Whether measuring the states whose blocks start at ``starts`` costs the next
        recovery no solve of the whole state."""
        ...

    def invalidate(self) -> None:
        """``I`` or ``x`` were replaced from outside: start again at the next recovery."""
        ...

    def corrections(self) -> AbstractContextManager:
        """A context in which what is added to ``I`` corrects rather than measures."""
        ...

    def pose_covariance(self, cols: IntArray) -> Array | None:
        """(7, 7) marginal of pose entries ``cols`` where cheap, else None."""
        ...

    def feature_covariances(self, filt: "InformationFilter", cols: IntArray) -> Array:
        """(F, 3, 3) marginals of features whose first entries are ``cols``; NaN where not cheap."""
        ...

    def propagate(self, filt: "InformationFilter", pose_starts: IntArray, starts: IntArray,
                  G: Array) -> Array | None:
        """``G P G^T`` for the joint marginal of the given poses and features, where cheap."""
        ...

    def state_dict(self) -> dict | None:
        """What a session keeps of the recovery (None: nothing)."""
        ...

    def load_state_dict(self, incremental: Any, online: Any, n: int) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        ...


class FullRecovery:
    """Every recovery is the full sparse solve of ``I x = i``; covariances come from its
    factorisation (cached by the filter)."""

    incremental = None
    online = None

    def fresh(self) -> "FullRecovery":
        return FullRecovery()

    def information_store(self) -> InformationStore:
        return InformationStore()

    def recover(self, filt: "InformationFilter") -> Array:
        return filt.recover()

    def recover_rebuilt(self, filt: "InformationFilter") -> Array:
        return filt.recover()

    def complete(self, filt: "InformationFilter", x: Array) -> Array:
        return x  # nothing is marginalised

    def recent(self, filt: "InformationFilter", steps: int) -> Array:
        return filt.x

    def measured_within(self, starts: IntArray, steps: int | None) -> NDArray[np.bool_]:
        return np.ones(np.shape(starts), bool)

    def recent_entries(self, steps: int, n: int) -> IntArray | None:
        return None

    def affordable(self, starts: IntArray) -> bool:
        return True

    def invalidate(self) -> None:
        pass

    def corrections(self) -> AbstractContextManager:
        return nullcontext()

    def pose_covariance(self, cols: IntArray) -> Array | None:
        return None  # the filter's factorisation answers

    def feature_covariances(self, filt: "InformationFilter", cols: IntArray) -> Array:
        full = filt.factor().covariance(np.asarray(cols, np.int64).reshape(-1, 3).ravel())
        return dense_diagonal_blocks(full)

    def propagate(self, filt: "InformationFilter", pose_starts: IntArray, starts: IntArray,
                  G: Array) -> Array | None:
        factor = filt.cached_factor()
        if factor is None:  # not cheap: only poses need it
            return None if len(pose_starts) else np.zeros((G.shape[0], G.shape[0]))
        cols = np.concatenate([block_entries(pose_starts, POSE_DIM), block_entries(starts)])
        return G @ factor.covariance(cols) @ G.T

    def state_dict(self) -> dict | None:
        return None

    def load_state_dict(self, incremental: Any, online: Any, n: int) -> None:
        if incremental is not None:
            raise SessionError("entry 'incremental' does not match the configured recovery")


class WindowRecovery:
    """Exact over an active window of recent states, the rest marginalised
    (:class:`~.incremental.IncrementalRecovery`); with ``online``, the window's measurements
    whose states moved are relinearised before each recovery.

    Parameters
    ----------
    window : int
        Steps without a measurement before a state leaves the window.
    online : OnlineRelinearisation, optional
    """

    def __init__(self, window: int, online: OnlineRelinearisation | None = None) -> None:
        self.incremental: IncrementalRecovery = IncrementalRecovery(window, window)
        self.online = online

    def fresh(self) -> "WindowRecovery":
        inc = self.incremental
        out = WindowRecovery(inc.feature_window, None if self.online is None else
                             OnlineRelinearisation(self.online.threshold))
        out.incremental = dataclasses.replace(inc, stats=RecoveryStats())
        return out

    def information_store(self) -> InformationStore:
        info = TrackedInformationStore()
        info.listeners.append(self.incremental)
        if self.online is not None:
            info.listeners.append(self.online)
        return info

    def recover(self, filt: "InformationFilter") -> Array:
        if self.online is not None:  # relinearise the window's measurements that moved
            self.online.step(filt)
        try:
            self.incremental.step(filt.layout, filt.info, filt.x)
        except EstimatorError:
            # the dense window could not be solved (numerically indefinite): rebuild it at
            # the next step and use the full sparse solve for this one
            self.incremental.on_invalidate()
            self.incremental.stats.fallbacks += 1
            return filt.recover()
        return filt.x

    def recover_rebuilt(self, filt: "InformationFilter") -> Array:
        inc = self.incremental
        inc.on_invalidate()
        try:
            inc.step(filt.layout, filt.info, filt.x)
        except EstimatorError:
            inc.on_invalidate()
            return filt.recover()
        inc.full_solution(filt.x)
        if not np.all(np.isfinite(filt.x)):
            inc.on_invalidate()
            raise EstimatorError("state recovery produced non-finite values")
        return filt.x

    def complete(self, filt: "InformationFilter", x: Array) -> Array:
        if self.incremental.valid:
            self.incremental.full_solution(x)
        return x

    def recent(self, filt: "InformationFilter", steps: int) -> Array:
        if self.incremental.valid:
            self.incremental.recent_solution(filt.x, 2 * int(steps))
        return filt.x

    def measured_within(self, starts: IntArray, steps: int | None) -> NDArray[np.bool_]:
        inc = self.incremental
        return inc.measured_within(starts, inc.feature_window if steps is None else steps)

    def recent_entries(self, steps: int, n: int) -> IntArray | None:
        return self.incremental.recent_entries(steps, n)

    def affordable(self, starts: IntArray) -> bool:
        return self.incremental.reactivation_affordable(starts)

    def invalidate(self) -> None:
        self.incremental.on_invalidate()

    def corrections(self) -> AbstractContextManager:
        return self.incremental.not_measuring()

    def pose_covariance(self, cols: IntArray) -> Array | None:
        return self.incremental.pose_covariance(cols)

    def feature_covariances(self, filt: "InformationFilter", cols: IntArray) -> Array:
        return self.incremental.feature_covariances(np.asarray(cols, np.int64).reshape(-1, 3)[:, 0])

    def propagate(self, filt: "InformationFilter", pose_starts: IntArray, starts: IntArray,
                  G: Array) -> Array | None:
        return self.incremental.propagate(pose_starts, starts, G)

    def state_dict(self) -> dict | None:
        return self.incremental.state_dict()

    def load_state_dict(self, incremental: Any, online: Any, n: int) -> None:
        if incremental is None:
            raise SessionError("entry 'incremental' does not match the configured recovery")
        self.incremental.load_state_dict(incremental, n)
        if self.online is not None and online is not None:
            self.online.load_state_dict(online, n)
