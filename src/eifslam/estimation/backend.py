"""What the system asks of a back end: the :class:`Backend` protocol.

Two classes satisfy it: the exactly sparse EIF,
:class:`~eifslam.estimation.filter.InformationFilter`, and the dense EKF baseline,
:class:`~eifslam.baselines.ekf.DenseEKF`. They share the linearisation of every
measurement (:mod:`eifslam.estimation.factors`) and the state layout
(:class:`~eifslam.estimation.state.StateLayout`), not an implementation:
:class:`~eifslam.system.slam.Slam` takes either as ``backend``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .measurements import FeatureObservations, RelativePose
from .options import FilterConfig
from .state import StateLayout

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

    def fuse_features(self, obs: FeatureObservations, store: bool = True, gate: bool = True) -> FeatureObservations:
        """Fuse a batch of ``Zm``; return the measurements kept."""
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

    def feature_covariances(self, track_ids) -> Array:
        """``(N, 3, 3)`` marginal covariances of map features where they are cheap, NaN
        elsewhere (the localisation's cut, :func:`~eifslam.estimation.localisation.localise_pose`)."""
        ...


__all__ = ["Backend"]
