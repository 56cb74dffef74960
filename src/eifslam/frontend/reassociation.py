"""Re-association of known tracks (:class:`TrackReassociation`, a base of
:class:`~eifslam.frontend.frontend.FrontEnd`): guided matching of lost ``Ωm`` tracks
(:meth:`~TrackReassociation.reobserve`), relocalisation against older frames and the
joining of tracks a verified loop found.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["TrackReassociation"]


class TrackReassociation:
    """Merging of tracks that are the same point seen again: the methods of the
    :class:`~eifslam.frontend.frontend.FrontEnd` (the class that sets ``_frames``,
    ``_desc``, ``_index``, ``_matcher``, ``_tracks``, ``_last_frame``, ``_last_kp`` and
    provides ``_get`` and ``_epipolar_matches``) that merge a frame's tracks into older
    ones."""

    def reobserve(self, frame_id: int, track_ids: IntArray, uv_predicted: Array, radius_px: float,
                  ratio: float | None = None) -> int:
        """Guided matching: find known ``Ωm`` tracks again in a frame where tracking lost them.

        Each track's descriptor (from its last observation) is matched against all the
        frame's keypoints (the front end's matcher: FLANN or Hamming); the nearest is
        taken when it passes the ratio test against the second nearest, lies within
        ``radius_px`` of where the track is predicted, and started a new ``Ωm`` track in
        this frame, which is then merged into the old track (so the map feature gets this
        measurement and the keypoint's measurements are never used twice).

        Parameters
        ----------
        frame_id : int
            A stored frame with descriptors.
        track_ids : (M,) int64
            ``Ωm`` track ids (current identities) not seen in the frame.
        uv_predicted : (M, 2)
            Undistorted pixels where each track is expected in the frame.
        radius_px : float
            Search radius, pixels.
        ratio : float, optional
            Ratio-test threshold (default: the matcher's).

        Returns
        -------
        int
            How many tracks were found again.
        """
        fid = int(frame_id)
        fr = self._get(fid)
        track_ids = np.asarray(track_ids, np.int64).reshape(-1)
        uv_predicted = np.asarray(uv_predicted, float).reshape(-1, 2)
        if len(track_ids) == 0 or fid not in self._desc or len(fr.feats) < 2:
            return 0
        ratio = self._matcher.ratio if ratio is None else float(ratio)
        lf, lk = self._last_frame[track_ids], self._last_kp[track_ids]
        have = (lf >= 0) & (lf != fid) & np.isin(lf, list(self._desc))
        track_ids, uv_predicted, lf, lk = track_ids[have], uv_predicted[have], lf[have], lk[have]
        if len(track_ids) == 0:
            return 0
        D = np.stack([self._desc[int(f)][int(k)] for f, k in zip(lf, lk)])
        Dk = self._desc[fid]
        # Lowe's ratio test over the whole frame (the radius only checks where the nearest
        # descriptor is): nearest and second-nearest keypoint of each track's descriptor
        index = self._index[fid] if fid in self._index else self._matcher.index(Dk)  # kept from matching
        nn, dd = index.knn(D.astype(Dk.dtype), 2)
        two = nn[:, 1] >= 0
        best = np.where(two, nn[:, 0], 0)
        d1 = np.where(two, dd[:, 0], np.inf)
        d2 = np.where(two, dd[:, 1], 0.0)
        ok = (d1 < ratio * d2) & (np.linalg.norm(fr.feats.uv[best] - uv_predicted, axis=1) <= radius_px)
        kid = self._tracks.resolve(fr.raw_ids)
        fresh = self._tracks.in_map(kid) & (self._tracks.length(kid) == 1)
        ok &= fresh[best]
        # a keypoint goes to one track only: the closest descriptor wins
        cand = np.flatnonzero(ok)
        cand = cand[np.argsort(d1[cand])]
        _, first = np.unique(best[cand], return_index=True)
        found = 0
        for i in cand[np.sort(first)]:
            if self._tracks.merge(int(track_ids[i]), int(kid[best[i]])):
                self._last_frame[track_ids[i]], self._last_kp[track_ids[i]] = fid, best[i]
                found += 1
        return found

    def relocalise(self, frame_id: int, candidate_frame_ids) -> list[tuple[int, int]]:
        """Match a frame against older stored frames and merge the matched tracks.

        Map features (and ``Ωp`` tracks) seen in a candidate regain their identity in
        ``frame_id``: each matched pair of tracks is merged into the older id, unless the
        two tracks are of different sets or share a frame.

        Parameters
        ----------
        frame_id : int
            A stored frame (with descriptors).
        candidate_frame_ids : iterable of int
            Stored frames to try (those without descriptors are skipped).

        Returns
        -------
        list of (candidate_id, n_matches)
            Epipolar-consistent matches found with each candidate (0 when none).
        """
        fr = self._get(frame_id)
        out: list[tuple[int, int]] = []
        pairs = []
        for c in candidate_frame_ids:
            c = int(c)
            if c == int(frame_id) or c not in self._desc or int(frame_id) not in self._desc:
                out.append((c, 0))
                continue
            cf = self._get(c)
            ia, ib = self._epipolar_matches(fr.feats.uv, self._desc[int(frame_id)],
                                            cf.feats.uv, self._desc[c])
            out.append((c, int(len(ia))))
            if len(ia):
                pairs.append(np.stack([fr.raw_ids[ia], cf.raw_ids[ib]], 1))
        if pairs:
            self._merge_pairs(np.concatenate(pairs))
        return out

    def join_tracks(self, frame_id: int, keypoints: IntArray, track_ids: IntArray) -> None:
        """Merge the tracks of keypoints of a frame into known tracks (a verified loop): as
        :meth:`relocalise` merges matched pairs (same set, no shared frame)."""
        kp = np.asarray(keypoints, np.int64).reshape(-1)
        if kp.size:
            self._merge_pairs(np.stack([self._get(frame_id).raw_ids[kp], np.asarray(track_ids, np.int64)], 1))

    def _merge_pairs(self, pairs: IntArray) -> None:
        roots = np.unique(self._tracks.resolve(pairs.reshape(-1)))
        frames: dict[int, set[int]] = {int(r): set() for r in roots}
        for fid, fr in self._frames.items():
            ids = self._tracks.resolve(fr.raw_ids)
            for h in ids[np.isin(ids, roots)]:
                frames[int(h)].add(fid)
        for a, b in pairs:
            ra, rb = (int(v) for v in self._tracks.resolve(np.array([a, b])))
            if ra == rb or frames[ra] & frames[rb]:
                continue
            if self._tracks.merge(ra, rb):
                frames[min(ra, rb)] = frames[ra] | frames[rb]
