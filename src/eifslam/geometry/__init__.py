"""Layer 1, geometry: rotations and quaternions, the pinhole camera, the observation models.

Pure NumPy; imports nothing else of eifslam but :mod:`eifslam.errors`.

* :mod:`.rotations`: Hamilton quaternions ``[w, x, y, z]``, rotation vectors, skew matrices.
* :mod:`.camera`: :class:`~.camera.PinholeCamera` (intrinsics, undistortion).
* :mod:`.models`: the paper's measurement models ``Zm``, ``ZR``, ``ZT`` with analytic Jacobians.
"""
