"""The front end: images in, ``Zm`` (map observations) and ``ZR``/``ZT`` (relative poses) out.

>>> from eifslam.frontend import FrontEnd, FrontEndConfig   # doctest: +SKIP
>>> fe = FrontEnd(camera, FrontEndConfig(detector="sift"))  # doctest: +SKIP
>>> res = fe.add_frame(image, 0)                            # doctest: +SKIP

Modules: :mod:`.config` (parameters), :mod:`.features` (detection, OpenCV),
:mod:`.split` (Ωp/Ωm rule), :mod:`.matching` (descriptors, epipolar RANSAC, OpenCV),
:mod:`.tracks` (track ids), :mod:`.twoview` (Sampson error, refinement, parallax),
:mod:`.uncertainty` (first-order and unscented covariances), :mod:`.relative_pose`
(ZR/ZT with covariance), :mod:`.results` (result types), :mod:`.frontend` (the
:class:`FrontEnd`: tracks, tracks found again, its part of a session), :mod:`.places`
(place recognition), :mod:`.loop_verification` (geometric checks of a loop candidate),
:mod:`.wide` (wide-baseline matching).
The modules ``config, split, tracks, twoview, uncertainty, results, places`` import no
OpenCV.
"""

from typing import Any

from .config import FrontEndConfig
from .results import FrameFeatures, FrameResult, Reason, RelativePoseResult

__all__ = [
    "FrontEnd",
    "FrontEndConfig",
    "FrameFeatures",
    "FrameResult",
    "RelativePoseResult",
    "Reason",
]


def __getattr__(name: str) -> Any:
    # FrontEnd needs OpenCV; import it lazily so the pure modules stay cv2-free
    if name == "FrontEnd":
        from .frontend import FrontEnd

        return FrontEnd
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
