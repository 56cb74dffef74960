"""Layer 2, baselines: other back ends over the same measurements, for comparison.

* :mod:`.bundle_adjustment`: full bundle adjustment of every track (Schur-complement
  Levenberg-Marquardt with a robust kernel).
* :mod:`.ekf`: a dense EKF in covariance form (MonoSLAM's cost).

Pure NumPy/SciPy; import only :mod:`eifslam.geometry` and :mod:`eifslam.estimation`.
"""
