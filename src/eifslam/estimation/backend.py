"""What the system asks of a back end: the :class:`Backend` protocol.

Two classes satisfy it: the exactly sparse EIF,
:class:`~eifslam.estimation.filter.InformationFilter`, and the dense EKF baseline,
:class:`~eifslam.baselines.ekf.DenseEKF`. They share the linearisation of every
measurement (:mod:`eifslam.estimation.factors`) and the state layout
(:class:`~eifslam.estimation.state.StateLayout`), not an implementation:
:class:`~eifslam.system.slam.Slam` takes either as ``backend``.

The protocol lists every member the system (:mod:`eifslam.system`) and the run's outputs
(:mod:`eifslam.evaluation.outputs`) use. The batch steps (smoothing, loop correction,
scale recovery) are least-squares problems over the stored measurements in information
form: they run on :meth:`Backend.information_form` and the back end takes their result
with :meth:`Backend.set_from_information_form` (the EIF is its own information form).
``tests/test_backend_protocol.py`` runs ``Slam`` at the default settings on each.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .measurements import FeatureObservations, PriorStore, RelativePose
from .options import FilterConfig
from .state import StateLayout

if TYPE_CHECKING:
    from .filter import InformationFilter

Array = NDArray[np.float64]


@runtime_checkable
class Backend(Protocol):
    """A SLAM back end over camera poses ``[p (3), q (4)]`` and map features ``(3,)``.

    Poses are keyed by frame id, features by track id. Fusing only records (and, for
    the EIF, sums) linearised measurements; :meth:`recover` / :meth:`recover_active`
    update the estimate ``x``.
    """

    camera: PinholeCamera
    config: FilterConfig
    layout: StateLayout
    priors: PriorStore

    @property
    def dim(self) -> int:
        """Dimension of the state."""
        ...

    @property
    def x(self) -> Array:
        """Current estimate ``(dim,)`` (a view)."""
        ...

    def add_pose(self, frame_id: int, p: Array, q: Array) -> None:
        """Augment the state with a pose at the initial guess ``p (3,)``, ``q (4,)``."""
        ...

    def add_features(self, track_ids, X: Array) -> None:
        """Augment the state with features at ``X (N, 3)``, world frame."""
        ...

    def fix_pose(self, frame_id: int) -> None:
        """Gauge: strong prior on a pose at its current estimate."""
        ...

    def set_scale(self, frame_a: int, frame_b: int, distance: float | None = None) -> None:
        """Scale prior ``|p_b - p_a| = distance`` (state units)."""
        ...

    def linearise_features(self, obs: FeatureObservations, gate: bool = True) -> tuple:
        """``(ok (N,), idx, J, W, innov, chi2 (N,))`` of ``Zm`` at the current estimate
        (:func:`eifslam.estimation.factors.features`)."""
        ...

    def fuse_features(self, obs: FeatureObservations, store: bool = True, gate: bool = True,
                      recent: bool = True) -> FeatureObservations:
        """Fuse a batch of ``Zm``; return the measurements kept. ``recent=False``: measurements
        made earlier and fused late (the recovery's window does not take their states back
        for them)."""
        ...

    def fuse_relative(self, rps: list[RelativePose], store: bool = True) -> None:
        """Fuse ``ZR``/``ZT`` pairs."""
        ...

    def linearise_relative(self, rps: list[RelativePose]) -> tuple:
        """``(idx (N, 14), J (N, 5, 14), W (N, 5, 5), innov (N, 5))`` at the current estimate."""
        ...

    def recover(self) -> Array:
        """Full recovery of the estimate; returns ``x``."""
        ...

    def recover_active(self) -> Array:
        """Per-frame recovery; returns ``x``."""
        ...

    def complete_estimate(self) -> Array:
        """Bring every state to the current solution; returns ``x``."""
        ...

    def recent_features(self, track_ids, steps: int | None = None) -> NDArray[np.bool_]:
        """Which map features ``(N,)`` were measured in the last ``steps`` recoveries (None:
        those in the active window, the local map; all of them where the back end does
        not tell)."""
        ...

    def local_map(self, steps: int) -> tuple[NDArray[np.int64], Array]:
        """Track ids ``(F,)`` and positions ``(F, 3)`` of the map features measured in the
        last ``steps`` recoveries (every feature where the back end does not tell), at a
        cost that does not grow with the map where it can tell."""
        ...

    def affordable_features(self, track_ids) -> bool:
        """Whether new measurements of these map features cost the next recovery no solve
        of the whole state (True where the back end does not tell)."""
        ...

    def recent_estimate(self, steps: int) -> Array:
        """Bring the states of about the last ``steps`` keyframes to the current solution,
        at a cost that does not grow with the map; returns ``x``."""
        ...

    def set_estimate(self, x: Array) -> None:
        """Replace the estimate by ``x (dim,)`` (e.g. a bundle adjustment's)."""
        ...

    def information_form(self) -> "InformationFilter":
        """The problem as an information filter at the current estimate, for the batch
        steps (:func:`~eifslam.estimation.smoothing.smooth`,
        :func:`~eifslam.estimation.loop_correction.correct_loop`,
        :func:`~eifslam.estimation.scale.recover_scale`)."""
        ...

    def set_from_information_form(self, filt: "InformationFilter") -> None:
        """Take the estimate (and what else a batch step changed) from ``filt``, made by
        :meth:`information_form`."""
        ...

    def pose(self, frame_id: int) -> tuple[Array, Array]:
        """``(p (3,), q (4,) unit)`` of a pose."""
        ...

    def poses(self) -> tuple[list[int], Array, Array]:
        """Frame ids, positions ``(P, 3)``, unit quaternions ``(P, 4)``."""
        ...

    def features(self) -> tuple[list[int], Array]:
        """Track ids and positions ``(F, 3)``."""
        ...

    def pose_covariance(self, frame_id: int) -> Array:
        """6x6 covariance of ``[p, dtheta]`` of a pose (``dtheta`` in rad)."""
        ...

    def feature_covariance(self, track_id: int) -> Array:
        """3x3 covariance of a map feature."""
        ...

    def propagate(self, frame_ids, track_ids, G: Array) -> Array | None:
        """``G P G^T`` for the joint covariance ``P`` of poses ``[p, q]`` (7 columns of
        ``G`` each) and map features (3 each), in the order given; None when it is not
        cheap (the EIF's poses outside its window)."""
        ...

    def feature_propagate(self, track_ids, G: Array) -> Array:
        """``G P G^T`` for the joint covariance of map features (zero where it is not cheap)."""
        ...

    def feature_covariances(self, track_ids) -> Array:
        """``(N, 3, 3)`` marginal covariances of map features where they are cheap, NaN
        elsewhere (the localisation's cut, :func:`~eifslam.estimation.localisation.localise_pose`)."""
        ...

    def information_matrix(self) -> sp.csc_matrix:
        """The information matrix ``(dim, dim)`` (the EKF: ``P^-1``), for the run's outputs."""
        ...


__all__ = ["Backend"]
