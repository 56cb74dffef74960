"""Layer 2, estimation: the exactly sparse EIF and what it is made of (pure NumPy/SciPy).

* :mod:`.state`: the state layout (which entries of ``x`` belong to which pose or feature).
* :mod:`.measurements`: ``Zm`` batches, ``ZR``/``ZT`` relative poses and their store.
* :mod:`.information`: the information matrix ``I`` and vector ``i`` as they are summed.
* :mod:`.options`: :class:`~.options.FilterConfig` and the typed options ``Recovery``, ``NoiseEstimate``.
* :mod:`.factors`: every measurement kind linearised at an estimate (shared by the back ends).
* :mod:`.recovery`: sparse Cholesky with features eliminated first (the full solve).
* :mod:`.blocks`: the 3x3 feature and 7x7 pose blocks: gathered, factorised, inverted, applied in batches.
* :mod:`.window`: the active window's marginal information, its solve and its eliminations.
* :mod:`.backsub`: the conditionals of what left the window and their back-substitution.
* :mod:`.reactivation`: undoing eliminations when a marginalised state is measured again.
* :mod:`.incremental`: the incremental recovery driver, which owns the window and the conditionals.
* :mod:`.filter`: :class:`~.filter.InformationFilter`, Algorithm 1's fusion (eq. 8).
* :mod:`.backend`: the :class:`~.backend.Backend` protocol the EIF and the dense EKF satisfy.
* :mod:`.gauss_newton`: the relinearise-then-solve pass that smoothing, loop correction and the online relinearisation share.
* :mod:`.smoothing`: relinearise-and-recover (III-E); :mod:`.scale`: scale recovery (V).
* :mod:`.calibration`: the focal length the smoothed map's ``Zm`` support, tested against the camera's.
* :mod:`.initialisation`, :mod:`.localisation`: initial guesses of poses and features.

Imports only :mod:`eifslam.geometry` and :mod:`eifslam.errors`; never OpenCV or matplotlib.
"""
