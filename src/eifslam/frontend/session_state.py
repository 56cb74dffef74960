"""What a session keeps of the front end (:class:`FrontEndState`, a base of
:class:`~eifslam.frontend.frontend.FrontEnd`): its frames as arrays, checked on loading.

:mod:`eifslam.system.session` writes these arrays into a ``.npz`` read with
``allow_pickle=False``; nothing a user's file contains is executed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import SessionError
from ..estimation.statedict import check_index, sub, take, take_ids
from .features import Features
from .tracks import TrackStore

IntArray = NDArray[np.int64]

__all__ = ["FrontEndState", "StoredFrame"]


@dataclass
class StoredFrame:
    """One stored frame of the front end."""

    feats: Features
    raw_ids: IntArray  # as assigned; resolve through the TrackStore before use


class FrontEndState:
    """The session half of the front end: :meth:`state_dict` and :meth:`load_state_dict`
    of the frames, descriptors and tracks a :class:`~eifslam.frontend.frontend.FrontEnd`
    holds (the class that sets ``_frames``, ``_order``, ``_desc``, ``_tracks``,
    ``_last_frame``, ``_last_kp`` and ``config``)."""

    def state_dict(self) -> dict:
        """What a session keeps, as arrays (:mod:`eifslam.estimation.statedict`): every
        stored frame's keypoints, descriptors and raw track ids (concatenated in frame
        order, ``n_keypoints`` per frame), which frames can still be matched, the track
        store and where each track was last seen. The detector and matcher are not kept
        (they are made from the config)."""
        frames = [self._frames[f] for f in self._order]

        def cat(get, tail: tuple, dtype) -> NDArray:
            parts = [np.asarray(get(f)).reshape((-1,) + tail) for f in frames]
            return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros((0,) + tail, dtype)

        desc = [f.feats.descriptors for f in frames if f.feats.descriptors.size]
        width, dtype = (desc[0].shape[1], desc[0].dtype) if desc else (0, np.uint8)
        D = cat(lambda f: f.feats.descriptors, (width,), dtype)
        # OpenCV's SIFT descriptors are floats holding integers 0..255: kept as bytes (4x
        # smaller), exactly
        as_bytes = D.dtype == np.float32 and bool(np.all((D >= 0) & (D <= 255) & (D == np.round(D))))
        return {
            "descriptors_float32": as_bytes,
            "order": np.array(self._order, np.int64),
            "n_keypoints": np.array([len(f.feats) for f in frames], np.int64),
            "matchable": np.array([f in self._desc for f in self._order], bool),
            "uv": cat(lambda f: f.feats.uv, (2,), float),
            "uv_raw": cat(lambda f: f.feats.uv_raw, (2,), float),
            "descriptors": D.astype(np.uint8) if as_bytes else D,
            "scale_px": cat(lambda f: f.feats.scale_px, (), float),
            "response": cat(lambda f: f.feats.response, (), float),
            "sign": cat(lambda f: f.feats.sign, (), np.int8),
            "colors": cat(lambda f: f.feats.colors, (3,), np.uint8),
            "raw_ids": cat(lambda f: f.raw_ids, (), np.int64),
            "tracks": self._tracks.state_dict(),
            "last_frame": self._last_frame.copy(),
            "last_kp": self._last_kp.copy(),
        }

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict` into this (new, empty) front end, checked.

        Raises
        ------
        SessionError
            On a missing, malformed or inconsistent entry.
        """
        if self._order:
            raise SessionError("a session loads into a new front end only")
        order = take_ids(d, "order")
        F = len(order)
        if len(np.unique(order)) != F:
            raise SessionError("array 'order' repeats a frame")
        nk = take_ids(d, "n_keypoints", F)
        matchable = take(d, "matchable", bool, (F,))
        N = int(nk.sum())
        uv, uv_raw = take(d, "uv", np.float64, (N, 2)), take(d, "uv_raw", np.float64, (N, 2))
        desc = take(d, "descriptors", (np.uint8, np.float32), (N, None))
        if d.get("descriptors_float32") is True and desc.dtype == np.uint8:
            desc = desc.astype(np.float32)
        scale, resp = take(d, "scale_px", np.float64, (N,)), take(d, "response", np.float64, (N,))
        sign, colors = take(d, "sign", np.int8, (N,)), take(d, "colors", np.uint8, (N, 3))
        want = (np.float32 if self.config.detector.float_descriptors else np.uint8, self._thread_detector().descriptorSize())
        if N and (desc.dtype, desc.shape[1]) != want:
            raise SessionError(f"descriptors are {desc.dtype} x {desc.shape[1]}, the detector's are "
                               f"{np.dtype(want[0])} x {want[1]}")
        raw = take_ids(d, "raw_ids", N)
        tracks = TrackStore()
        tracks.load_state_dict(sub(d, "tracks"))
        check_index(raw, len(tracks), "array 'raw_ids'")
        last_f, last_k = take_ids(d, "last_frame", None, -1), take_ids(d, "last_kp", None, -1)
        if len(last_f) != len(last_k) or len(last_f) > len(tracks):
            raise SessionError("arrays 'last_frame' and 'last_kp' do not match the tracks")
        n_of = dict(zip(order.tolist(), nk.tolist()))
        seen = last_f >= 0
        if not np.all(np.isin(last_f[seen], order)) or np.any(
                last_k[seen] >= np.array([n_of.get(f, 0) for f in last_f[seen].tolist()], np.int64)) \
                or np.any(last_k[seen] < 0):
            raise SessionError("arrays 'last_frame' and 'last_kp' name a keypoint that is not stored")
        ends = np.cumsum(nk)
        for fid, a, b, m in zip(order.tolist(), (ends - nk).tolist(), ends.tolist(), matchable.tolist()):
            feats = Features(uv[a:b].copy(), uv_raw[a:b].copy(), desc[a:b].copy(), scale[a:b].copy(),
                             resp[a:b].copy(), sign[a:b].copy(), colors[a:b].copy())
            self._frames[fid] = StoredFrame(feats, raw[a:b].copy())
            if m:
                self._desc[fid] = feats.descriptors
        self._order = order.tolist()
        self._tracks, self._last_frame, self._last_kp = tracks, last_f.copy(), last_k.copy()

