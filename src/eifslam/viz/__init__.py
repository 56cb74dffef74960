"""Live views of a run: :class:`~eifslam.viz.viewer.RerunViewer` streams each frame to the
rerun viewer or to an ``.rrd`` file (the optional ``viewer`` extra, ``rerun-sdk``)."""
