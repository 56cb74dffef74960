"""Pinhole camera model (pure NumPy).

Pixel convention: image origin top-left, pixel centres at integer coordinates, ``u`` to the
right, ``v`` down. Camera frame: ``x`` right, ``y`` down, ``z`` forward (optical axis).
Lens distortion (OpenCV's ``k1 k2 p1 p2 [k3]`` radial-tangential model) is removed by the
front end; every pixel that reaches the estimator is undistorted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..errors import CalibrationError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PinholeCamera:
    """Calibrated pinhole camera.

    Attributes
    ----------
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels.
    width, height : int
        Image size in pixels.
    distortion : tuple of float
        OpenCV radial-tangential coefficients ``(k1, k2, p1, p2[, k3])``; zeros if none.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            raise CalibrationError(f"camera intrinsics must be finite, got {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        if len(self.distortion) not in (0, 4, 5, 8):
            raise CalibrationError(
                f"distortion must have 4, 5 or 8 coefficients, got {len(self.distortion)}"
            )
        if not all(np.isfinite(self.distortion)):
            raise CalibrationError("distortion coefficients must be finite")

    @property
    def K(self) -> Array:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(np.asarray(self.distortion, dtype=float) != 0.0))

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view in degrees."""
        return float(np.degrees(2.0 * np.arctan2(self.width / 2.0, self.fx)))

    def project(self, X_c: Array) -> Array:
        """Project camera-frame points ``(..., 3)`` to pixels ``(..., 2)`` (no distortion)."""
        X_c = np.asarray(X_c, dtype=float)
        z = X_c[..., 2]
        return np.stack([self.fx * X_c[..., 0] / z + self.cx, self.fy * X_c[..., 1] / z + self.cy], -1)

    def normalized(self, uv: Array) -> Array:
        """Normalised image coordinates ``(..., 2)`` of undistorted pixels ``(..., 2)``."""
        uv = np.asarray(uv, dtype=float)
        return np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)

    def bearing(self, uv: Array) -> Array:
        """Unit bearing vectors ``(..., 3)`` in the camera frame of undistorted pixels."""
        n = self.normalized(uv)
        b = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], -1)
        return b / np.linalg.norm(b, axis=-1, keepdims=True)

    def in_image(self, uv: Array, margin: float = 0.0) -> NDArray[np.bool_]:
        """Mask of pixels ``(..., 2)`` inside the image (with ``margin`` pixels)."""
        uv = np.asarray(uv, dtype=float)
        return (
            (uv[..., 0] >= -0.5 + margin)
            & (uv[..., 0] <= self.width - 0.5 - margin)
            & (uv[..., 1] >= -0.5 + margin)
            & (uv[..., 1] <= self.height - 0.5 - margin)
        )

    def scaled(self, factor: float) -> "PinholeCamera":
        """The same camera for images resized by ``factor`` (pixel-centre convention)."""
        return PinholeCamera(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            distortion=self.distortion,
        )
