"""Layer 2, estimation: the exactly sparse EIF and what it is made of (pure NumPy/SciPy).

* :mod:`.state`: the state layout (which entries of ``x`` belong to which pose or feature).
* :mod:`.measurements`: ``Zm`` batches, ``ZR``/``ZT`` relative poses and their store.
* :mod:`.information`: the information matrix ``I`` and vector ``i`` as they are summed.
* :mod:`.recovery`: sparse Cholesky with features eliminated first (the full solve).
* :mod:`.incremental`: exact recovery over an active window, the rest marginalised.
* :mod:`.filter`: :class:`~.filter.InformationFilter`, Algorithm 1's fusion (eq. 8).
* :mod:`.smoothing`: relinearise-and-recover (III-E) and scale recovery (V).
* :mod:`.initialisation`, :mod:`.localisation`: initial guesses of poses and features.

Imports only :mod:`eifslam.geometry` and :mod:`eifslam.errors`; never OpenCV or matplotlib.
"""
