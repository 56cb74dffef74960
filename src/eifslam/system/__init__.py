"""Layer 4, system: the SLAM system a user runs.

* :mod:`.config`: :class:`~.config.SlamConfig`, the one set of defaults, validated.
* :mod:`.slam`: :class:`~.slam.Slam`, Algorithm 1 over a stream of images.
* :mod:`.runner`: drive a :class:`~.slam.Slam` over a sequence with a progress bar.
"""
