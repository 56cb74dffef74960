"""Per-frame recovery of the information filter through its incremental window
(:mod:`.incremental`), as a mixin of :class:`~eifslam.estimation.filter.InformationFilter`
(its own attributes; kept apart so that the filter module stays about filtering)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError

Array = NDArray[np.float64]

__all__ = ["WindowRecoveryMixin"]


class WindowRecoveryMixin:
    """``recover_active``, ``recover_rebuilt`` and ``complete_estimate`` of
    :class:`~eifslam.estimation.filter.InformationFilter`."""

    # -- incremental recovery (eifslam.estimation.incremental) -------------------------------------
    def recover_active(self) -> Array:
        """Per-frame recovery: exact over the active window (``recovery="incremental"``;
        other states keep their last estimate) or :meth:`recover` (``"full"``)."""
        if self.incremental is None:
            return self.recover()
        if self.online is not None:  # relinearise the window's measurements that moved
            self.online.step(self)
        try:
            self.incremental.step(self.layout, self.info, self._x[: self.dim])
        except EstimatorError:
            # the dense window could not be solved (numerically indefinite): rebuild it at
            # the next step and use the full sparse solve for this one
            self.incremental.on_invalidate()
            self.incremental.stats.fallbacks += 1
            return self.recover()
        return self.x

    def recover_rebuilt(self) -> Array:
        """:meth:`recover`, in incremental mode by rebuilding the recovery window (about one
        full solve) and back-substituting: the window is valid afterwards, so after
        :meth:`relinearise` the next :meth:`recover_active` needs no second rebuild."""
        if self.incremental is None:
            return self.recover()
        inc = self.incremental
        inc.on_invalidate()
        try:
            inc.step(self.layout, self.info, self._x[: self.dim])
        except EstimatorError:
            inc.on_invalidate()
            return self.recover()
        inc.full_solution(self._x[: self.dim])
        if not np.all(np.isfinite(self.x)):
            inc.on_invalidate()
            raise EstimatorError("state recovery produced non-finite values")
        return self.x

    def recent_estimate(self, steps: int) -> Array:
        """Incremental mode: back-substitute the states marginalised in about the last
        ``steps`` recovery steps (exact for those, bounded cost; older ones keep their
        values until :meth:`complete_estimate`). Full mode: nothing to do."""
        if self.incremental is not None and self.incremental.valid:
            self.incremental.recent_solution(self._x[: self.dim], 2 * int(steps))
        return self.x

    def complete_estimate(self) -> Array:
        """Incremental mode: back-substitute every marginalised state (``O(n)``), so that
        ``x`` equals the full solve of the information as of the last
        :meth:`recover_active`. Full mode: nothing to do."""
        if self.incremental is not None and self.incremental.valid:
            self.incremental.full_solution(self._x[: self.dim])
        return self.x
