"""Layer 4, system: the SLAM system a user runs.

* :mod:`.config`: :class:`~.config.SlamConfig`, the one set of defaults, validated;
  :class:`~.config.Mode`.
* :mod:`.slam`: :class:`~.slam.Slam`, the front object: Algorithm 1 over a stream of
  images, ``finish()`` as the mode says, sessions.
* :mod:`.tracking`: :class:`~.tracking.Tracker`, placing a frame in the state.
* :mod:`.mapping`: :class:`~.mapping.Mapper`, map observations, new features, fusion.
* :mod:`.finishing`: after the run (bundle-adjustment glue, :class:`~.finishing.FinishReport`).
* :mod:`.session`: save and load a whole :class:`~.slam.Slam`.
* :mod:`.runner`: drive a :class:`~.slam.Slam` over a sequence with a progress bar.

This layer imports no evaluation, io, cli or plotting code.
"""

from .config import Mode, SlamConfig
from .slam import Slam, TrackingState, TrackResult

__all__ = ["Mode", "Slam", "SlamConfig", "TrackResult", "TrackingState"]
