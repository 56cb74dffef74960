"""Evaluation and reporting: metrics (pure NumPy/evo), outputs, the HTML report, plots.

:mod:`.metrics` imports neither OpenCV nor matplotlib; :mod:`.plots` and
:mod:`.plots_eval` draw on a given matplotlib ``Axes``; :mod:`.outputs` writes a run's files
and :mod:`.report` the HTML page.
"""
