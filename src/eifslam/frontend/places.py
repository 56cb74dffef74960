"""Place recognition: a bag of visual words over the run's frames, with an inverted index.

The vocabulary is learnt online from the run itself: the descriptors of the first
``train_frames`` frames that are added (a seeded subsample of each) are clustered by
scikit-learn's :class:`~sklearn.cluster.MiniBatchKMeans` into ``n_words`` visual words;
from then on every added frame is a TF-IDF vector (inverse document frequencies from the
training frames, fixed once learnt, so stored vectors never change), L2-normalised. The
frames that arrived before the vocabulary existed are indexed the moment it is learnt.

Binary descriptors (ORB, AKAZE) are unpacked to 0/1 floats: the squared Euclidean
distance between two unpacked descriptors is their Hamming distance, so k-means and the
nearest-word assignment work in Hamming space without a binary-specific library.

A word is the nearest word centre (one matrix product, so a loaded session needs only
the centres, not a pickled estimator); the database is a sparse frame-by-word matrix
(scipy), and a query is one sparse product (cosine similarity) that touches only the
frames sharing a word with the query (an inverted index by word).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from ..errors import SessionError
from ..estimation.statedict import take, take_ids

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["PlaceIndex", "descriptor_features"]


def descriptor_features(descriptors: NDArray) -> NDArray[np.float32]:
    """Descriptors as float vectors for the vocabulary: binary ``uint8`` descriptors are
    unpacked to 0/1 bits (squared Euclidean distance = Hamming distance), float ones are
    kept."""
    d = np.asarray(descriptors)
    if d.dtype == np.uint8:
        return np.unpackbits(d.reshape(len(d), -1), axis=1).astype(np.float32)
    return np.asarray(d, np.float32).reshape(len(d), -1)


def _fit_vocabulary(X: NDArray[np.float32], n_words: int, seed: int) -> NDArray[np.float32]:
    """Word centres ``(n_words, D)``: scikit-learn's mini-batch k-means of ``X (N, D)``, with
    its BLAS and OpenMP held to one thread. It runs beside tracking and the prefetch worker
    (and, when a short run ends first, at exit): with the libraries' own thread counts it
    took 18 s of CPU for 20 castle frames' ORB descriptors on a loaded 2-core machine,
    against 1.7 s in one thread, for the same centres. (The BLAS limit is process-wide
    while it lasts; the runner holds BLAS to ``runtime.blas_threads``, 1, anyway.)

    One k-means++ initialisation on 1024 of the descriptors: the run joins k-means at a
    fixed frame (``learn_lag``), and it must be done by then or tracking waits. On 20
    frames of kitti-seq1 (300 descriptors each, one quiet thread) the best of three
    initialisations on ``3 * batch_size`` descriptors costs 2.6 s of CPU with ORB's 256
    unpacked bits and 1.45 s with SIFT (tracking waited 0.7-3.3 s at the join on five
    shared sets with ORB), one on 1024 0.4 s and 0.3 s, for an inertia 1.1% (ORB) and
    1.2% (SIFT) higher."""
    from sklearn.cluster import MiniBatchKMeans
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        km = MiniBatchKMeans(n_clusters=n_words, random_state=seed, n_init=1, init_size=1024, batch_size=2048,
                             max_iter=50).fit(X)
    return km.cluster_centers_.astype(np.float32)


class PlaceIndex:
    """Bag-of-words image database (DBoW-style) of one run.

    Parameters
    ----------
    n_words : int
        Visual words (k-means clusters).
    train_frames : int
        Frames whose descriptors train the vocabulary.
    per_frame : int
        At most this many descriptors of each frame, for training and for its word
        histogram (a seeded random subset).
    seed : int
        Seed of the subsampling and of k-means (a run is repeatable).
    learn_lag : int
        k-means runs in a background thread while this many more frames arrive (they
        are indexed, late, when it is joined); the vocabulary and the frame at which it
        is joined depend only on the frames, never on the thread's timing. 0: learn in
        the calling thread.
    """

    def __init__(self, n_words: int = 256, train_frames: int = 20, per_frame: int = 300, seed: int = 0,
                 learn_lag: int = 5) -> None:
        self.n_words = int(n_words)
        self.train_frames = int(train_frames)
        self.per_frame = int(per_frame)
        self.seed = int(seed)
        self.learn_lag = max(int(learn_lag), 0)
        self._learning: tuple[int, Future] | None = None  # (training frames, k-means in flight)
        self._centres: NDArray[np.float32] | None = None
        self._c64 = np.zeros((0, 0))  # the centres in double precision, and their squared norms
        self._c2 = np.zeros(0)
        self._idf = np.zeros(0)
        self._pending: list[tuple[int, NDArray[np.float32]]] = []  # frames waiting for the vocabulary
        self._ids: list[int] = []
        self._rows: list[sp.csr_matrix] = []
        self._matrix: sp.csr_matrix | None = None

    # -- queries ------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        """Whether the vocabulary has been learnt."""
        return self._centres is not None

    @property
    def frame_ids(self) -> list[int]:
        """Indexed frames, in the order they were indexed."""
        return list(self._ids)

    def vector(self, frame_id: int) -> sp.csr_matrix | None:
        """The TF-IDF vector ``(1, n_words)`` of an indexed frame, or None."""
        try:
            return self._rows[self._ids.index(int(frame_id))]
        except ValueError:
            return None

    def scores(self, frame_id: int, candidates) -> Array:
        """Cosine similarity between an indexed frame and each of ``candidates`` (0 for a
        candidate that is not indexed)."""
        v = self.vector(frame_id)
        cand = [int(c) for c in candidates]
        if v is None or not cand:
            return np.zeros(len(cand))
        s = self.query(v)
        pos = {f: i for i, f in enumerate(self._ids)}
        return np.array([s[pos[c]] if c in pos else 0.0 for c in cand])

    def query(self, v: sp.csr_matrix) -> Array:
        """Cosine similarity of a TF-IDF vector with every indexed frame, in
        :attr:`frame_ids` order (one sparse product over the word-major database)."""
        if not self._ids:
            return np.zeros(0)
        if self._matrix is None:
            self._matrix = sp.vstack(self._rows, format="csr")
        elif self._matrix.shape[0] != len(self._rows):  # append the new rows only
            self._matrix = sp.vstack([self._matrix, *self._rows[self._matrix.shape[0]:]], format="csr")
        return np.asarray((self._matrix @ v.T).toarray()).reshape(-1)

    # -- updates ------------------------------------------------------------------
    def add(self, frame_id: int, descriptors: NDArray) -> bool:
        """Add a frame's descriptors ``(N, D)``; returns whether it is indexed (False while
        the vocabulary is still being gathered)."""
        d = np.asarray(descriptors)
        rng = np.random.default_rng(self.seed + int(frame_id))
        if len(d) > self.per_frame:  # a seeded subset: the word histogram of 300 is as telling, and cheaper
            d = d[np.sort(rng.choice(len(d), self.per_frame, replace=False))]
        F = descriptor_features(d)
        if self.ready:
            self._index(int(frame_id), F)
            return True
        self._pending.append((int(frame_id), F))
        if self._learning is None and len(self._pending) >= self.train_frames:
            # the training frames: the shortest prefix of at least train_frames frames with
            # 2 descriptors per word (else keep gathering); a prefix, so that a session
            # saved while k-means runs trains the same vocabulary when resumed
            total = np.cumsum([len(F) for _, F in self._pending])
            ok = np.flatnonzero((np.arange(1, len(total) + 1) >= self.train_frames) & (total >= 2 * self.n_words))
            if len(ok):
                n = int(ok[0]) + 1
                fit = partial(_fit_vocabulary, np.concatenate([F for _, F in self._pending[:n] if len(F)]),
                              self.n_words, self.seed)
                if self.learn_lag:
                    pool = ThreadPoolExecutor(max_workers=1)
                    future = pool.submit(fit)
                    pool.shutdown(wait=False)  # the thread ends once k-means returns
                else:
                    future = Future()
                    future.set_result(fit())
                self._learning = (n, future)
        if self._learning is not None and len(self._pending) >= self._learning[0] + self.learn_lag:
            self._learn()
        return self.ready

    def _learn(self) -> None:
        """Join k-means (the first ``n`` pending frames trained it) and index every pending frame."""
        n, future = self._learning
        self._learning = None
        self._set_vocabulary(future.result(), None)
        counts = np.zeros(self.n_words)
        words = [self._words(F) for _, F in self._pending]
        for w in words[:n]:
            counts[np.unique(w)] += 1
        self._idf = np.log((1.0 + n) / (1.0 + counts)) + 1.0  # smoothed IDF over the training frames
        pending, self._pending = self._pending, []
        for (fid, F), w in zip(pending, words):
            self._append(fid, w)

    def __getstate__(self) -> dict:
        """Pickle without k-means in flight: the copy starts it again at its next frame, on
        the same frames (so it joins at the same frame, with the same vocabulary)."""
        return {**self.__dict__, "_learning": None}

    def _set_vocabulary(self, centres: NDArray[np.float32], idf: Array | None) -> None:
        self._centres = centres
        self._c64 = np.asarray(centres, np.float64)
        self._c2 = np.einsum("ij,ij->i", self._c64, self._c64)
        if idf is not None:
            self._idf = idf

    def _words(self, F: NDArray[np.float32]) -> IntArray:
        """The nearest word centre of each row of ``F (N, D)`` (brute force, Euclidean):
        the argmin of ``|c|^2 - 2 f.c`` (``|f - c|^2`` less the row constant ``|f|^2``) in
        double precision, one matrix product (scikit-learn's ``pairwise_distances_argmin``
        gives the same words at 4-5 times the cost per frame)."""
        if len(F) == 0:
            return np.zeros(0, np.int64)
        return np.argmin(self._c2[None, :] - 2.0 * (np.asarray(F, np.float64) @ self._c64.T), axis=1).astype(np.int64)

    def _index(self, frame_id: int, F: NDArray[np.float32]) -> None:
        self._append(frame_id, self._words(F))

    def _append(self, frame_id: int, words: IntArray) -> None:
        tf = np.bincount(words, minlength=self.n_words).astype(float)
        v = tf / max(tf.sum(), 1.0) * self._idf
        v /= max(float(np.linalg.norm(v)), 1e-300)
        self._ids.append(frame_id)
        self._rows.append(sp.csr_matrix(v.reshape(1, -1)))

    # -- sessions -----------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps: the word centres and IDF (when learnt), the frames still
        waiting for the vocabulary (their subsampled descriptors) and every indexed
        frame's vector (CSR rows)."""
        M = sp.vstack(self._rows, format="csr") if self._rows else sp.csr_matrix((0, self.n_words))
        pend = [F for _, F in self._pending]
        width = pend[0].shape[1] if pend else 0
        return {
            "centres": np.zeros((0, 0), np.float32) if self._centres is None else self._centres,
            "idf": np.asarray(self._idf, float),
            "pending_ids": np.array([f for f, _ in self._pending], np.int64),
            "pending_n": np.array([len(F) for F in pend], np.int64),
            "pending": np.concatenate(pend) if pend else np.zeros((0, width), np.float32),
            "ids": np.array(self._ids, np.int64),
            "indptr": M.indptr.astype(np.int64),
            "indices": M.indices.astype(np.int64),
            "data": M.data.astype(float),
        }

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        C = take(d, "centres", np.float32, (None, None))
        if C.size:
            if C.ndim != 2 or C.shape[0] != self.n_words:
                raise SessionError("place index: vocabulary of the wrong size")
            self._set_vocabulary(C, take(d, "idf", np.float64, (self.n_words,)))
        pid = take_ids(d, "pending_ids")
        pn = take_ids(d, "pending_n", len(pid))
        P = take(d, "pending", np.float32, (None, None))
        if int(pn.sum()) != len(P):
            raise SessionError("place index: pending descriptors do not add up")
        self._pending = list(zip(pid.tolist(), np.split(P, np.cumsum(pn)[:-1]) if len(pn) else []))
        ids = take_ids(d, "ids")
        indptr = take_ids(d, "indptr", len(ids) + 1)
        indices = take_ids(d, "indices")
        data = take(d, "data", np.float64, (len(indices),))
        if len(ids) and (indptr[-1] != len(indices) or np.any(indices >= self.n_words)):
            raise SessionError("place index: bad word vectors")
        M = sp.csr_matrix((data, indices, indptr), shape=(len(ids), self.n_words)) if len(ids) else None
        self._ids = ids.tolist()
        self._rows = [M[i] for i in range(len(ids))] if M is not None else []
        self._matrix = None
