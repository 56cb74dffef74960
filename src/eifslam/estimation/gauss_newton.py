"""The relinearise-then-solve pass shared by smoothing, loop correction and the online
relinearisation (pure NumPy/SciPy).

One Gauss-Newton pass over the stored measurements is: remember the estimate ``x``,
rebuild ``I`` and ``i`` from zero at it
(:meth:`~eifslam.estimation.filter.InformationFilter.relinearise`, paper III-E), solve, and
measure the step against the scale of the map. :func:`begin_pass` does the first two and
returns a :class:`GaussNewtonPass` that measures, tests and undoes the step; how the
system is solved is the caller's:

* :func:`gauss_newton` runs plain passes with a given solve until the step is small
  (:func:`~eifslam.estimation.loop_correction.relinearise_all` after a loop closure);
* :func:`~eifslam.estimation.smoothing.smooth` solves each pass damped when the plain step
  raises the cost (Levenberg-Marquardt);
* the online relinearisation
  (:class:`~eifslam.estimation.relinearisation.OnlineRelinearisation`) replaces, instead of
  rebuilding everything, the terms of single measurements; a measurement's terms at its
  linearisation point are :func:`information_terms` (eq. 8), as in the batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError

if TYPE_CHECKING:  # the passes call only the filter's public methods
    from .filter import InformationFilter

Array = NDArray[np.float64]

__all__ = ["GaussNewtonPass", "begin_pass", "gauss_newton", "information_terms", "state_scale"]


def information_terms(J: Array, W: Array, rhs: Array) -> tuple[Array, Array]:
    """Paper eq. 8's terms of ``N`` measurements: ``(J^T W J (N, k, k), J^T W rhs (N, k))``
    for Jacobians ``J (N, m, k)``, weights ``W (N, m, m)`` and ``rhs (N, m)`` (the
    innovation plus ``J`` times the linearisation point, or the measured value of a prior)."""
    JtW = np.swapaxes(J, 1, 2) @ W
    return JtW @ J, np.einsum("nkm,nm->nk", JtW, rhs)


def state_scale(filt: "InformationFilter") -> float:
    """The unit a step is measured in: ``max(1, scale prior length)`` (1 without one)."""
    return 1.0 if filt.priors.scale is None else max(1.0, filt.priors.scale[2])


@dataclass
class GaussNewtonPass:
    """A pass begun by :func:`begin_pass`: ``I``, ``i`` relinearised at ``before``.

    Attributes
    ----------
    before : (n,) the estimate the information was relinearised at.
    fused : (N,) bool, which stored ``Zm`` the relinearised information holds.
    """

    before: Array
    fused: NDArray[np.bool_]

    def change(self, filt: "InformationFilter") -> float:
        """Largest change of a state entry since :attr:`before` (state units)."""
        return float(np.max(np.abs(filt.x - self.before))) if filt.dim else 0.0

    def converged(self, filt: "InformationFilter", tol: float) -> bool:
        """Whether the step changed no entry by more than ``tol`` times :func:`state_scale`."""
        return self.change(filt) <= tol * state_scale(filt)

    def undo(self, filt: "InformationFilter") -> None:
        """Back to the estimate :attr:`before` (the information stays as relinearised)."""
        filt.x[:] = self.before


def begin_pass(filt: "InformationFilter") -> GaussNewtonPass:
    """Relinearise every stored measurement at the current estimate (``I``, ``i`` rebuilt
    from zero); the caller then solves."""
    before = filt.x.copy()
    return GaussNewtonPass(before, filt.relinearise())


def gauss_newton(filt: "InformationFilter", passes: int, tol: float,
                 solve: Callable[[int], object]) -> int:
    """Plain Gauss-Newton passes: :func:`begin_pass`, then ``solve(n)`` (``n`` the pass
    number, from 0; it writes the solution into ``filt.x``), until a pass converges
    (:meth:`GaussNewtonPass.converged`) or ``passes`` were run. A pass whose solve raises
    :class:`~eifslam.errors.EstimatorError` is undone (the estimate before it, with its
    information relinearised there again) and the passes stop.

    Returns
    -------
    int
        Passes kept.
    """
    done = 0
    for n in range(int(passes)):
        p = begin_pass(filt)
        try:
            solve(n)
        except EstimatorError:
            p.undo(filt)
            filt.relinearise()
            break
        done += 1
        if p.converged(filt, tol):
            break
    return done
