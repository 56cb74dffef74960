"""Re-association of known tracks (:class:`TrackReassociation`, a base of
:class:`~eifslam.frontend.frontend.FrontEnd`): guided matching of lost ``Ωm`` tracks
(:meth:`~TrackReassociation.reobserve`), relocalisation against older frames and the
joining of tracks a verified loop found.
"""

from __future__ import annotations

from itertools import chain

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .matching import descriptor_distance

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
        """Guided search: find known ``Ωm`` tracks again in a frame where tracking lost them.

        Each track's descriptor (from its last observation) is compared only with the
        frame's keypoints near where the track is predicted (active search: no matching
        against the whole frame). The nearest descriptor within ``radius_px`` is taken when
        it passes the ratio test against the second nearest within ``2 radius_px`` (the
        neighbourhood that tells a distinctive match from a repeated texture) and started a
        new ``Ωm`` track in this frame; that track is then merged into the old one (so the
        map feature gets this measurement and the keypoint's measurements are never used
        twice). A track with no second descriptor in its neighbourhood is not taken.

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
        Dk = self._desc[fid]
        pairs = cKDTree(fr.feats.uv).query_ball_point(uv_predicted, 2.0 * float(radius_px))
        n_cand = np.fromiter((len(c) for c in pairs), np.int64, len(pairs))
        rows = np.flatnonzero(n_cand >= 2)
        if len(rows) == 0:
            return 0
        track_of = np.repeat(rows, n_cand[rows])
        kp = np.fromiter(chain.from_iterable(pairs[r] for r in rows), np.int64, int(n_cand[rows].sum()))
        D = np.stack([self._desc[int(f)][int(k)] for f, k in zip(lf[rows], lk[rows])])
        Dt = D[np.searchsorted(rows, track_of)]
        dist = descriptor_distance(Dt, Dk[kp])
        # per track: nearest and second nearest in the neighbourhood (sorted by track, then distance)
        order = np.lexsort((dist, track_of))
        track_of, kp, dist = track_of[order], kp[order], dist[order]
        first = np.flatnonzero(np.r_[True, track_of[1:] != track_of[:-1]])
        best, d1, d2 = kp[first], dist[first], dist[first + 1]
        t_idx = track_of[first]
        near = np.linalg.norm(fr.feats.uv[best] - uv_predicted[t_idx], axis=1) <= radius_px
        kid = self._tracks.resolve(fr.raw_ids)
        fresh = self._tracks.in_map(kid) & (self._tracks.length(kid) == 1)
        ok = (d1 < ratio * d2) & near & fresh[best]
        # a keypoint goes to one track only: the closest descriptor wins
        cand = np.flatnonzero(ok)
        cand = cand[np.argsort(d1[cand], kind="stable")]
        _, keep = np.unique(best[cand], return_index=True)
        found = 0
        for i in cand[np.sort(keep)]:
            t = int(track_ids[t_idx[i]])
            if self._tracks.merge(t, int(kid[best[i]])):
                self._last_frame[t], self._last_kp[t] = fid, best[i]
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
