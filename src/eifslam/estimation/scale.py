"""Scale recovery (paper V), pure NumPy / SciPy.

Scale recovery rescales the state by ``s`` so that one known length (between two
features, or two poses) is met. Every measurement of this problem is invariant to scale,
so the rescaled estimate satisfies them equally well; the information transforms exactly
by the diagonal similarity ``S = diag(s on positions, 1 on quaternions)``:
``I' = S^-1 I S^-1``, ``i' = S^-1 i`` (then ``I' (S x) = i'``), and covariances of positions
scale by ``s^2``. This costs one pass over the non-zeros and no refactorisation. (The
paper suggests a Sherman-Morrison rank-one update, i.e. fusing the known length as one
more scalar measurement; with the scale already fixed by a gauge prior that update would
be a compromise between the two lengths, so the similarity transform, which replaces the
gauge length, is what we do.)
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import EstimatorError
from .filter import InformationFilter
from .state import StateKey, StateKind


def rescale(filt: InformationFilter, s: float) -> None:
    """Multiply every position in the state by ``s`` and transform ``I``, ``i`` consistently.

    ``I' = S^-1 I S^-1``, ``i' = S^-1 i`` with ``S = diag(s on positions, 1 on
    quaternions)``; the stored priors scale too. ``s`` is dimensionless, positive.
    """
    if not (np.isfinite(s) and s > 0):
        raise EstimatorError(f"scale factor must be positive and finite, got {s}")
    pos = filt.layout.position_mask()
    d = np.where(pos, 1.0 / s, 1.0)
    Sinv = sp.diags(d)
    I = Sinv @ filt.info.matrix() @ Sinv
    i = d * filt.info.vector
    filt.info.set(sp.csc_matrix(I), i)
    filt.x[pos] *= s
    if filt.priors.scale is not None:
        a, b, dist = filt.priors.scale
        filt.priors.scale = (a, b, dist * s)
    filt.priors.pose = {k: (p * s, q) for k, (p, q) in filt.priors.pose.items()}
    filt.priors.weak = {k: (v * s if k[0] == StateKind.FEATURE else np.concatenate([v[:3] * s, v[3:]]))
                        for k, v in filt.priors.weak.items()}
    filt.invalidate()


def recover_scale(filt: InformationFilter, a: StateKey | tuple[str, int], b: StateKey | tuple[str, int],
                  length: float) -> float:
    """Rescale so that the distance between states ``a`` and ``b`` is ``length``.

    Parameters
    ----------
    a, b : StateKey or tuple
        ``(StateKind.FEATURE, track_id)`` or ``(StateKind.POSE, frame_id)``; plain
        ``("feature", track_id)`` / ``("pose", frame_id)`` work too.
    length : float
        The true distance, in the units wanted for the map.

    Returns
    -------
    float
        The factor applied.
    """
    a, b = StateKey.of(a), StateKey.of(b)
    lay, x = filt.layout, filt.x
    cur = float(np.linalg.norm(lay.position(b, x) - lay.position(a, x)))
    if not cur > 0:
        raise EstimatorError("the two states coincide; their distance cannot set the scale")
    if not (np.isfinite(length) and length > 0):
        raise EstimatorError(f"known length must be positive, got {length}")
    s = length / cur
    rescale(filt, s)
    return s


__all__ = ["recover_scale", "rescale"]
