"""What the measurements say about the focal length (pure NumPy / SciPy).

The filter takes the camera's intrinsics as given. A focal length a few percent off is
absorbed by the estimate where the motion turns: most of a turn's image motion is
rotation, whose image displacement is proportional to the focal length, and what the
rotation leaves unexplained is taken as translation, so the scale of the turn follows the
focal length. :func:`focal_check` tests the given focal length against the stored ``Zm``
at the current estimate: one Gauss-Newton step of the joint problem in the states and a
common factor ``phi`` of ``fx`` and ``fy``, with the states eliminated exactly (the
information matrix bordered by one column, solved with the filter's own factorisation).

With ``h = (phi fx X/Z + cx, phi fy Y/Z + cy)``, ``dh/dphi`` at ``phi = 1`` is ``h - c``
(the prediction's offset from the principal point). The step is

    dphi = (d - b^T I^-1 g) / (c - b^T I^-1 b),

``b = sum J^T W (h - c)`` over the ``Zm`` (an ``n``-vector), ``c = sum (h - c)^T W (h - c)``,
``d = sum (h - c)^T W r`` (``r`` the innovations), ``g = i - I x`` the states' remaining
Gauss-Newton right-hand side. Its standard deviation is ``s / sqrt(c - b^T I^-1 b)`` with
``s`` the pixel noise the residuals show over the stated one, and the cost falls by
``dphi^2 (c - b^T I^-1 b) / s^2`` (chi-square with one degree of freedom when the given
focal length is right). ``ZR``/``ZT`` are left out: they were computed from the images
with the given intrinsics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .filter import InformationFilter


@dataclass(frozen=True)
class FocalCheck:
    """The focal length the ``Zm`` support, relative to the given one.

    Attributes
    ----------
    scale : float
        ``1 + dphi``: the factor of ``fx`` and ``fy`` one joint Gauss-Newton step reaches.
    sigma : float
        Its standard deviation (at the residuals' noise).
    chi2 : float
        The cost the step removes, at the residuals' noise (chi-square, 1 DOF, when the
        given focal length is right and the model holds; real images, with tens of
        thousands of ``Zm`` and model errors of their own, exceed its quantiles for
        offsets of a fraction of a percent).
    """

    scale: float
    sigma: float
    chi2: float

    def as_dict(self) -> dict:
        return asdict(self)


def focal_check(filt: "InformationFilter", noise_scale: float = 1.0) -> FocalCheck | None:
    """Test the camera's focal length against the stored ``Zm`` at ``filt.x`` (see the
    module); ``noise_scale``: the residuals' pixel noise over the stated one (``s``).

    ``filt``'s information and estimate are left as they are. Returns None when there is
    nothing to test (no usable ``Zm``, or ``phi`` not constrained once the states are
    eliminated).
    """
    obs = filt.store.all_features()
    if len(obs) == 0:
        return None
    # the information at x of exactly the Zm it holds (a feature whose views no longer
    # constrain it keeps its weak prior, and its Zm stay out of b and c too); the filter's
    # own information is put back afterwards
    I0, i0 = filt.info.matrix().copy(), filt.information_vector()
    try:
        fused = filt.relinearise()
        if not np.any(fused):
            return None
        _, idx, J, W, innov, _ = filt.linearise_features(obs, gate=False)
        idx, J, W, innov = idx[fused], J[fused], W[fused], innov[fused]
        cam = filt.camera
        jphi = obs.uv[fused] - innov - np.array([cam.cx, cam.cy])  # (N, 2): dh/dphi = h - c
        Wj = np.einsum("nij,nj->ni", W, jphi)
        c = float(np.sum(jphi * Wj))
        d = float(np.sum(innov * Wj))
        b = np.zeros(filt.dim)
        np.add.at(b, idx, np.einsum("nmk,nm->nk", J, Wj))
        F = filt.factor()
        u = F.solve(b)
        step = F.solve(filt.information_vector()) - filt.x  # I^-1 g
    finally:
        filt.info.set(I0, i0)
        filt.invalidate()
    schur = c - float(b @ u)
    if not (np.isfinite(schur) and schur > 1e-9 * c):
        return None
    dphi = (d - float(b @ step)) / schur
    s2 = max(float(noise_scale), 1e-6) ** 2
    stat = dphi**2 * schur / s2
    return FocalCheck(1.0 + dphi, float(np.sqrt(s2 / schur)), float(stat))


__all__ = ["FocalCheck", "focal_check"]
