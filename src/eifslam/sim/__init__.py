"""Simulation: scenes with known answers.

* :mod:`.synthetic`: measurement-level scenes (corridor, orbit) and simulated ``Zm``,
  ``ZR``/``ZT`` (pure NumPy).
* :mod:`.frontend`: :class:`~.frontend.SyntheticFrontEnd`, those measurements behind the
  front end's interface, so that :class:`eifslam.system.slam.Slam` runs on them (pure
  NumPy).
* :mod:`.two_view`: two-view scenes for the front end's tests (pure NumPy).
* :mod:`.scene`: the built-in scene of the paper's first experiment, rendered to images
  (its rendering uses OpenCV).
"""
