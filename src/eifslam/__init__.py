"""eifslam: monocular SLAM with an exactly sparse Extended Information Filter.

Implements Wang & Dissanayake, "Efficient Monocular SLAM using sparse information
filters" (ICIAfS 2010). The mathematical core (geometry, camera, observation models,
information filter, recovery, smoothing, synthetic scenes, evaluation) is pure
NumPy/SciPy; OpenCV and matplotlib are used only by the front end, loaders and plots.
"""

__version__ = "0.1.0"
