"""Incremental exact state recovery over an active window (paper III-G; pure NumPy/SciPy).

The paper obtains the Cholesky factor ``L(k)`` of the information matrix from ``L(k-1)``.
During an exploration this is possible because a new image only touches recent states:
the current pose, the previous one, and the features in view. In the chronological
elimination order the factor of every state that is never touched again is final.

This module keeps the *marginal* information of an active window of states, in the
structure of the reduced camera system:

* active poses: a dense block ``P`` (``7 p x 7 p``) and vector ``bp``;
* active features: 3x3 blocks ``D`` (no measurement involves two features) and vector
  ``bf``, coupled to the active poses only, by ``B`` (``3 f x 7 p``, dense).

A new measurement whose states are all active adds into ``P``, ``D``, ``B``, ``b``
directly. Each step solves the window exactly (Schur complement onto the poses, dense
Cholesky) in ``O(f p^2)``, independent of the map size, then marginalises:

* features not measured for ``feature_window`` steps: ``P -= B_f^T D_f^-1 B_f`` (fill
  only among poses);
* poses not measured for ``pose_window`` steps *and* no longer coupled to an active
  feature: ``P -= P_kq P_qq^-1 P_qk`` (fill only among poses again).

So the window keeps its structure forever. Each elimination stores its conditional
(``x_q = A^-1 (b_q - C x_rest)``), which is one block row of a Cholesky factorisation in
elimination order: the full state follows by back substitution in reverse order in
``O(n)`` (:meth:`IncrementalRecovery.full_solution`). The result is exact (equal to the
full sparse solve). When a measurement touches a marginalised state (loop closure,
relocalisation, a feature seen again after a gap, a frame localised late, earlier
observations of a newly triangulated feature), the state is re-activated: its
conditional is undone (``C^T A^-1 C`` added back to the window, its rows re-inserted),
after the conditionals of the later-eliminated poses it was conditioned on, as iSAM2
re-eliminates the path to the root of its Bayes tree (:mod:`.reactivation`); no access
to the full ``I``. That path grows with the time since the state left: a loop closure
after a long exploration would bring back hundreds of poses into the dense window
(minutes at 100,000 entries); a pose batch is undone only in part when only some of
its poses are needed (the rest is eliminated again onto the window and those poses).
So the work is estimated first
(:func:`~eifslam.estimation.reactivation.reactivation_flops`) and,
when it exceeds the cost of one full sparse solve (:meth:`IncrementalRecovery.rebuild_flops`),
or when a state lies inside a rebuild's sparse factorisation (which cannot be undone),
the window is rebuilt from the full sparse ``I`` instead (counted as a fallback): the
eliminated part into one feature batch and one dense pose batch when it holds at most
``undoable_rebuild_pose_entries`` pose entries (undoable like any marginalisation, so a
revisit after a rebuild re-activates instead of rebuilding again), else into one sparse
factorisation (:func:`eifslam.estimation.recovery.reduced_onto`, the features' elimination kept from
the previous one for those no fusion touched since: :mod:`.elimination`); a window over the
recent states and the touched ones, and every state back-substituted, so ``x`` is the full
solution at that frame; the frames after it are constant time again. Rebuilding also
follows :meth:`InformationStore.reset` / ``set`` (smoothing, rescaling).
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping, Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_solve

from ..errors import ConfigError, EstimatorError, SessionError
from .information import InformationStore, SummedRows, block
from .elimination import FeatureElimination
from .statedict import sub, take_ids, take_int
from .state import FEATURE_DIM, POSE_DIM, StateKind, StateLayout
from . import reactivation
from .backsub import Conditional, Conditionals
from .reactivation import ReactivationPlan
from .blocks import block_diagonal_csr, inverse_spd_blocks, pose_cholesky, sparse_diagonal_blocks
from .window import ActiveWindow

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class RecoveryStats:
    """Counters of :class:`IncrementalRecovery`.

    Attributes
    ----------
    steps : recoveries done.
    fallbacks : steps where a measurement touched a marginalised state that could not be
        re-activated (full rebuild), plus solves that failed (see
        :meth:`eifslam.estimation.filter.InformationFilter.recover_active`).
    rebuilds : full rebuilds for any reason (fallbacks, ``I`` reset/set, first use).
    reactivations : steps where a measurement touched marginalised states and they were
        re-activated (their conditionals undone, no rebuild).
    reactivated_poses, reactivated_features : states brought back into the window so far
        (the touched ones and the later-eliminated poses they were conditioned on).
    marginalised_poses, marginalised_features : states eliminated so far (re-eliminations
        included).
    window_poses, window_features : size of the active window after the last step.
    max_window_poses : largest number of active poses solved in one step.
    indefinite_solves : steps whose pose Schur complement was numerically indefinite
        (solved by ``LDL^T`` instead of Cholesky; see :meth:`ActiveWindow.solve`).
    """

    steps: int = 0
    fallbacks: int = 0
    rebuilds: int = 0
    reactivations: int = 0
    reactivated_poses: int = 0
    reactivated_features: int = 0
    marginalised_poses: int = 0
    marginalised_features: int = 0
    window_poses: int = 0
    window_features: int = 0
    max_window_poses: int = 0
    indefinite_solves: int = 0


class InformationListener(Protocol):
    """Something told about every fusion and every wholesale change of ``I``, ``i``."""

    def on_add(self, idx: IntArray, Lam: Array, eta: Array) -> None: ...

    def on_invalidate(self) -> None: ...


class TrackedInformationStore(InformationStore):
    """An :class:`InformationStore` that reports every ``add`` to its listeners.

    ``reset`` and ``set`` (smoothing, rescaling) report ``on_invalidate``.
    """

    def __init__(self) -> None:
        super().__init__()
        self.listeners: list[InformationListener] = []

    def add(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        super().add(idx, Lam, eta)
        if len(idx):
            for lis in self.listeners:
                lis.on_add(idx, Lam, eta)

    def add_split(self, idx: IntArray, Lam: Array, eta: Array, split: int) -> None:
        super().add_split(idx, Lam, eta, split)
        if len(idx):
            for lis in self.listeners:
                lis.on_add(idx, Lam, eta)

    def reset(self) -> None:
        super().reset()
        for lis in self.listeners:
            lis.on_invalidate()

    def set(self, I: sp.spmatrix, i: Array) -> None:
        super().set(I, i)
        for lis in self.listeners:
            lis.on_invalidate()


class EntryMap:
    """Per-entry kind and block start of the state, followed as the layout grows.

    Attributes
    ----------
    n : int                 entries seen so far.
    start : (n,) int        state index of the first entry of each entry's block.
    is_feature : (n,) bool  whether an entry belongs to a feature.
    """

    def __init__(self) -> None:
        self.n = 0
        self._nblocks = 0
        self._start = np.zeros(1024, np.int64)
        self._isf = np.zeros(1024, bool)

    @property
    def start(self) -> IntArray:
        return self._start[: self.n]

    @property
    def is_feature(self) -> NDArray[np.bool_]:
        return self._isf[: self.n]

    def sync(self, layout: StateLayout) -> list[tuple[bool, int]]:
        """Follow the layout; return ``(is_feature, offset)`` of the blocks added since."""
        new = []
        for kind, ident in layout.keys_since(self._nblocks):
            isf = kind == StateKind.FEATURE
            new.append((isf, layout.feature_offset(ident) if isf else layout.pose_offset(ident)))
        self._nblocks = layout.n_states
        if layout.dim > len(self._start):
            cap = max(layout.dim, 2 * len(self._start))
            self._start = np.concatenate([self._start, np.zeros(cap - len(self._start), np.int64)])
            self._isf = np.concatenate([self._isf, np.zeros(cap - len(self._isf), bool)])
        for isf, off in new:
            size = FEATURE_DIM if isf else POSE_DIM
            self._start[off : off + size] = off
            self._isf[off : off + size] = isf
        self.n = layout.dim
        return new


@dataclass
class IncrementalRecovery:
    """Exact recovery of ``I x = i`` restricted to an active window, updated per step.

    The driver: it follows the layout and the fusions, decides what to rebuild,
    re-activate and marginalise. It owns the active window (:attr:`window`, an
    :class:`~eifslam.estimation.window.ActiveWindow`) and the conditionals of the states
    that left it (:attr:`conditionals`, :class:`~eifslam.estimation.backsub.Conditionals`),
    which do the algebra, and re-activates through :mod:`~eifslam.estimation.reactivation`.

    Parameters
    ----------
    feature_window : int
        A feature is marginalised after this many steps without a measurement (>= 1).
    pose_window : int
        A pose is marginalised after this many steps without a measurement, once no
        active feature is coupled to it (>= 1).
    full_solve_flops_per_entry : float
        Cost model of a rebuild (about one full sparse solve), in dense floating-point
        operations per state entry: a measurement of marginalised states re-activates
        them when :meth:`reactivation_flops` is at most ``max(min_rebuild_flops, this * n)``, and
        rebuilds the window from one sparse factorisation otherwise (a loop closure
        after a long exploration). 2e4 makes a rebuild worth ~2e9 dense operations at
        100,000 entries, where it takes ~2 s (``docs/backend.md``).
    min_rebuild_flops : float
        Floor of that cost model (small states: re-activation is cheap either way).
    rebuild_horizon : int
        A rebuild keeps in the window every state measured within this many steps (at
        least the windows), so that they are marginalised again one by one into
        conditionals that can be undone: a feature seen again after a short gap then
        re-activates instead of rebuilding once more (a sparse factorisation cannot be
        undone).
    undoable_rebuild_pose_entries : int
        A rebuild that eliminates at most this many pose entries (300 poses) does so as
        :meth:`_marginalise` does, into a feature batch and one dense pose batch
        (:meth:`_eliminate_undoably`), so that a state measured again after a rebuild is
        re-activated (only the poses its features need come back, see
        :func:`~eifslam.estimation.reactivation.reactivate`) instead
        of rebuilding once more: on a sequence that keeps revisiting old places, one
        rebuild per frame otherwise. Larger eliminations use one sparse factorisation
        (:func:`~eifslam.estimation.recovery.reduced_onto`; ``q x q`` dense would cost
        ``O(q^3)``), which cannot be undone. 0: always the sparse factorisation.
    """

    feature_window: int = 2
    pose_window: int = 2
    stats: RecoveryStats = field(default_factory=RecoveryStats)
    full_solve_flops_per_entry: float = 2e4
    min_rebuild_flops: float = 1e9
    rebuild_horizon: int = 10
    undoable_rebuild_pose_entries: int = 2100

    def __post_init__(self) -> None:
        for key in ("feature_window", "pose_window", "rebuild_horizon"):
            v = getattr(self, key)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ConfigError(f"{key} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.undoable_rebuild_pose_entries, (int, np.integer))
                and self.undoable_rebuild_pose_entries >= 0):
            raise ConfigError(f"undoable_rebuild_pose_entries must be an integer >= 0, "
                              f"got {self.undoable_rebuild_pose_entries!r}")
        for key in ("full_solve_flops_per_entry", "min_rebuild_flops"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{key} must be a non-negative number, got {v!r}")
        self._map = EntryMap()
        self._last = np.zeros(0, np.int64)  # step of the last measurement, at block starts
        self._pending: list[tuple[IntArray, Array, Array, bool]] = []  # (idx, Lam, eta, a measurement?)
        self._measuring = True
        self._valid = False
        self._late: list[IntArray] = []  # entries measured while the window was invalid
        self._elim = FeatureElimination()  # the sparse rebuilds' feature elimination, kept
        self.window = ActiveWindow()
        self.conditionals = Conditionals()

    # -- pickling -----------------------------------------------------------------------
    def __getstate__(self) -> dict:
        """Pickle without the window and the conditionals (a rebuild's conditional holds a
        sparse factorisation, which does not pickle): the unpickled recovery is invalid
        and rebuilds from the full ``I`` at its next :meth:`step`. Pickle the owner's
        complete estimate (:meth:`full_solution`) if it is needed after loading."""
        state = self.__dict__.copy()
        state.update(window=ActiveWindow(len(self.window.pos)), conditionals=Conditionals(len(self.conditionals.owner)),
                     _pending=[], _late=[], _valid=False, _elim=FeatureElimination())
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    # -- sessions -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps: the step of each state's last measurement and the
        counters (the window is not kept; a loaded recovery rebuilds it, as an unpickled
        one does)."""
        return {"last": self._last.copy(), "stats": dataclasses.asdict(self.stats)}

    def load_state_dict(self, d: Mapping[str, Any], dim: int) -> None:
        """Restore :meth:`state_dict` into a fresh recovery of a filter of ``dim``
        entries; the window is invalid until the next :meth:`step` rebuilds it.

        Raises
        ------
        SessionError
            On a malformed entry.
        """
        last = take_ids(d, "last")
        if len(last) > dim:
            raise SessionError("array 'last' is longer than the state")
        st = sub(d, "stats")
        stats = RecoveryStats(**{f.name: take_int(st, f.name, 0) for f in dataclasses.fields(RecoveryStats)})
        if last.size and last.max() > stats.steps:
            raise SessionError("array 'last' holds a step after the last one")
        self.on_invalidate()
        self.stats, self._last = stats, last.copy()

    # -- listener -----------------------------------------------------------------------
    def on_add(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        """Record a fusion (processed at the next :meth:`step`). While the window is invalid
        only which states were measured is kept (the rebuild reads ``I``), so that the
        rebuild keeps them in the window: e.g. a loop's ``Zm`` of old features fused
        after the estimate was moved, which the next frames observe again."""
        self._elim.touch(idx)
        if self._valid:
            self._pending.append((idx, Lam, eta, self._measuring))
        elif self._measuring:
            self._late.append(np.asarray(idx, np.int64).ravel())

    @contextmanager
    def not_measuring(self) -> Iterator[None]:
        """Fusions inside this block are corrections (online relinearisation), not
        measurements: the states they touch do not count as measured again, so they leave
        the window when their last measurement is old enough."""
        self._measuring = False
        try:
            yield
        finally:
            self._measuring = True

    def on_invalidate(self) -> None:
        """``I`` was replaced wholesale: rebuild at the next step. Which states the fusions
        not yet stepped measured is kept (as for fusions while invalid, :meth:`on_add`)."""
        self._late += [p[0].ravel() for p in self._pending if p[3]]
        self._elim = FeatureElimination()  # I may have been replaced: eliminate afresh
        self._valid = False
        self._pending = []

    # -- the step -------------------------------------------------------------------------
    @property
    def valid(self) -> bool:
        """False once ``I`` was replaced wholesale and until the next step rebuilds."""
        return self._valid

    def step(self, layout: StateLayout, info: InformationStore, x: Array) -> None:
        """Fold the new fusions in, solve the window into ``x``, marginalise old states.

        Parameters
        ----------
        layout : the filter's state layout.
        info : the filter's information (used only to rebuild).
        x : (n,) the filter's estimate; active entries are overwritten with the exact
            solution of ``I x = i``, the others are left as they are.
        """
        if not any(lis is self for lis in getattr(info, "listeners", ())):
            raise EstimatorError("incremental recovery is not attached to this information store "
                                 "(was the store replaced?); use the full recovery")
        st = self.stats
        st.steps += 1
        s = st.steps
        new = self._map.sync(layout)
        n = self._map.n
        self._last = np.concatenate([self._last, np.full(n - len(self._last), s, np.int64)])
        w = self.window
        w.grow(n)
        self.conditionals.grow(n)
        pending, self._pending = self._pending, []
        touched = np.concatenate([p[0].ravel() for p in pending]) if pending else np.zeros(0, np.int64)
        measured = [p[0].ravel() for p in pending if p[3]] + self._late
        self._late = []
        if measured:
            self._last[self._map.start[np.concatenate(measured)]] = s
        restart = False
        if not self._valid:
            self._rebuild(info, s)
        else:
            w.append(new)
            marg = np.unique(self._map.start[touched[w.pos[touched] < 0]])
            plan = self.plan_reactivation(marg) if len(marg) else None
            if len(marg) and (plan is None or self.reactivation_flops(plan) > self.rebuild_flops()):
                st.fallbacks += 1
                self._rebuild(info, s)
                restart = True
            else:
                if len(marg):
                    self.reactivate(marg, plan)
                for idx, Lam, eta, _ in pending:
                    w.add(idx, Lam, eta, self._map.is_feature, self._map.start)
        if w.solve():
            st.indefinite_solves += 1
        w.write_solution(x)
        if restart:  # e.g. a loop closure: every state moved; one back substitution
            self.full_solution(x)
        st.max_window_poses = max(st.max_window_poses, len(w.pidx) // POSE_DIM)
        self._marginalise(s)
        st.window_poses, st.window_features = len(w.pidx) // POSE_DIM, len(w.fidx) // FEATURE_DIM

    def _marginalise(self, s: int) -> None:
        """Eliminate the features not measured for ``feature_window`` steps, then the poses
        not measured for ``pose_window`` steps that no active feature is coupled to."""
        w, last = self.window, self._last
        fstale = (s - last[w.fidx[::FEATURE_DIM]]) >= self.feature_window
        if np.any(fstale):
            self.conditionals.append(w.eliminate_features(fstale))
            self.stats.marginalised_features += int(fstale.sum())
        pstale = ((s - last[w.pidx[::POSE_DIM]]) >= self.pose_window) & ~w.coupled_poses()
        if np.any(pstale):
            self.conditionals.append(w.eliminate_poses(pstale))
            self.stats.marginalised_poses += int(pstale.sum())
        w.symmetrise()

    # -- re-activation ----------------------------------------------------------------------
    def plan_reactivation(self, blocks: IntArray) -> ReactivationPlan | None:
        """:func:`~eifslam.estimation.reactivation.plan_reactivation` of marginalised
        ``blocks`` (block starts) over this window and its conditionals."""
        return reactivation.plan_reactivation(blocks, self.window, self.conditionals, self._map.start)

    def reactivation_flops(self, plan: ReactivationPlan) -> float:
        """:func:`~eifslam.estimation.reactivation.reactivation_flops` of ``plan``."""
        return reactivation.reactivation_flops(plan, self.window, self.conditionals)

    def reactivate(self, blocks: IntArray, plan: ReactivationPlan | None = None) -> bool:
        """Bring marginalised states (block starts ``blocks``) back into the window by
        undoing their eliminations (:func:`~eifslam.estimation.reactivation.reactivate`;
        ``plan``: :meth:`plan_reactivation` of ``blocks`` when already made). Returns False,
        with nothing changed, when a requested state lies in a rebuild conditional (a
        sparse factorisation, which cannot be undone); True otherwise."""
        plan = self.plan_reactivation(blocks) if plan is None else plan
        if plan is None:
            return False
        reactivation.reactivate(plan, self.window, self.conditionals, self._map.start)
        st = self.stats
        st.reactivations += 1
        st.reactivated_poses += sum(len(v) for v in plan.poses.values())
        st.reactivated_features += sum(len(v) for v in plan.features.values())
        return True

    # -- the estimate and its covariances ---------------------------------------------------
    @property
    def active_indices(self) -> IntArray:
        """State indices of the active window (poses then features)."""
        return self.window.active_indices

    def full_solution(self, x: Array) -> Array:
        """Back-substitute every marginalised state into ``x`` (in place) in ``O(n)``
        (:class:`~eifslam.estimation.backsub.BackSubstitution`: the poses newest first,
        then the features in merged chunks).

        The window's solution is written into ``x`` first (as :meth:`step` left it);
        entries added to the layout after the last step are left untouched.
        """
        if not self.window.solved:
            return x  # the window changed without a solve: nothing consistent to add
        self.window.write_solution(x)
        return self.conditionals.back_substitute(x)

    def recent_solution(self, x: Array, slots: int) -> Array:
        """:meth:`full_solution` for the states of the last ``slots`` conditionals only
        (about two a step: one feature batch, one pose batch), exact for those; older
        marginalised states keep the values ``x`` has. A rebuild among those slots holds
        every state that was old then: of those, only the ones measured in the last
        ``slots / 2`` steps are recovered (what the other slots cover in a run without
        rebuilds), reading only their rows of the rebuild's coupling. The cost is bounded
        by ``slots``, not by the size of the state."""
        if not self.window.solved:
            return x
        self.window.write_solution(x)
        n = len(self._last)
        wanted = self._last[self._map.start[:n]] > self.stats.steps - max(int(slots) // 2, 1)
        return self.conditionals.back_substitute(x, start=len(self.conditionals) - int(slots), wanted=wanted)

    def pose_covariance(self, cols: IntArray) -> Array | None:
        """Marginal covariance of active pose entries ``cols`` (k,) from the window as last
        solved (:meth:`ActiveWindow.pose_covariance`); None when an entry is not an active
        pose or the window is stale."""
        return self.window.pose_covariance(cols) if self._valid else None

    def feature_covariances(self, starts: IntArray) -> Array:
        """Marginal covariances ``(F, 3, 3)`` of the features whose first entries are
        ``starts`` (F,) from the window as last solved
        (:meth:`ActiveWindow.feature_covariances`); NaN for a feature that was not active
        then, and for all when the window is stale."""
        if not self._valid:
            return np.full((np.size(starts), 3, 3), np.nan)
        return self.window.feature_covariances(starts)

    def propagate(self, pose_starts: IntArray, starts: IntArray, G: Array) -> Array | None:
        """``G P G^T`` for the joint marginal covariance ``P`` of active poses and features
        (:meth:`ActiveWindow.propagate`). When the window is stale: None if poses are asked
        for, else zero (the features count as exact)."""
        if not self._valid:
            return None if np.size(pose_starts) else np.zeros((np.shape(G)[0],) * 2)
        return self.window.propagate(pose_starts, starts, G)

    def reactivation_affordable(self, starts: IntArray) -> bool:
        """Whether new measurements of the states whose blocks start at ``starts`` would be
        taken in by re-activation rather than a rebuild: those of them marginalised can be
        planned (:meth:`plan_reactivation`) at a cost below a rebuild's (about one full
        solve)."""
        if not self._valid:
            return True
        starts = np.unique(np.asarray(starts, np.int64))
        pos = self.window.pos
        starts = starts[starts < len(pos)]
        marg = starts[pos[starts] < 0]
        if not len(marg):
            return True
        plan = self.plan_reactivation(marg)
        return plan is not None and self.reactivation_flops(plan) <= self.rebuild_flops()

    def measured_within(self, starts: IntArray, steps: int) -> NDArray[np.bool_]:
        """Whether the states whose blocks start at entries ``starts`` (any shape) were
        measured within the last ``steps`` steps, as of the last step (states added since
        count as measured now)."""
        starts = np.asarray(starts, np.int64)
        known = starts < len(self._last)
        last = self._last[np.where(known, starts, 0)] if len(self._last) else np.zeros(starts.shape, np.int64)
        return ~known | (self.stats.steps - last < steps)

    def recent_entries(self, steps: int, n: int) -> IntArray:
        """Entries of a state of dimension ``n`` measured within the last ``steps`` steps,
        as of the last step (the block starts of those states among them; the entries
        added since count as measured now): ``O(n)`` in NumPy over one integer array, not
        per state."""
        old = np.flatnonzero(self.stats.steps - self._last < steps)
        return np.concatenate([old, np.arange(len(self._last), max(int(n), len(self._last)))])

    def rebuild_flops(self) -> float:
        """The cost model of a rebuild (see ``full_solve_flops_per_entry``)."""
        return max(self.min_rebuild_flops, self.full_solve_flops_per_entry * self._map.n)

    # -- rebuild from the full information --------------------------------------------------
    def _rebuild(self, info: InformationStore, s: int) -> None:
        """Window = features measured within ``rebuild_horizon`` steps, their poses and
        recent poses (states just measured included, however old); the rest ``m`` is eliminated exactly from the
        full sparse ``I``: into a feature batch and a dense pose batch when it holds at most
        ``undoable_rebuild_pose_entries`` pose entries (:meth:`_eliminate_undoably`), else
        into one conditional: one sparse factorisation of ``I_mm`` (features first, on the
        entries of ``m``, without extracting ``I_mm``), and the marginal of the active
        poses ``I_aa - I_am I_mm^-1 I_ma`` from a second factorisation of the reduced pose
        system with the active poses ordered last
        (:func:`~eifslam.estimation.recovery.factorize_onto`): about the cost of one full
        solve."""
        self.stats.rebuilds += 1
        self._valid = True
        n = self._map.n
        I = info.rows()  # read by rows: the parts of I are not summed into one matrix
        i = np.asarray(info.vector[:n], dtype=float)
        isf, start = self._map.is_feature, self._map.start
        age = s - self._last[start]
        fa = np.flatnonzero(isf & (age < max(self.feature_window, self.rebuild_horizon)))
        pose_all = np.flatnonzero(~isf)
        Ifp = block(I, fa, pose_all)
        coupled = np.zeros(n, bool)
        coupled[pose_all[np.unique(Ifp.tocoo().col)]] = True
        blk_coupled = np.zeros(n, bool)
        blk_coupled[start[coupled]] = True
        pa = np.flatnonzero(~isf & ((age < max(self.pose_window, self.rebuild_horizon)) | blk_coupled[start]))
        active = np.zeros(n, bool)
        active[fa] = active[pa] = True
        m = np.flatnonzero(~active)
        self.conditionals.clear(n)
        mf, mp = m[isf[m]], m[~isf[m]]
        if len(m) and 0 < self.undoable_rebuild_pose_entries and len(mp) <= self.undoable_rebuild_pose_entries:
            P, bp = self._eliminate_undoably(I, i, pa, mf, mp)
        else:
            Ia = I[pa]  # (7p, n): the active poses' rows; I_ma is its transpose (I symmetric)
            if len(m):
                factor, P, bp = self._elim.onto(I, i, mp, mf, pa, pose_all, self._map.start)
                self.conditionals.append(Conditional(m, i[m].copy(), sp.csr_matrix(Ia.T)[m], pa,
                                                     factor=factor.restricted(m)))
            else:
                P, bp = Ia[:, pa].toarray(), i[pa].copy()
        D = sparse_diagonal_blocks(block(I, fa, fa))
        Ifa = Ifp[:, np.searchsorted(pose_all, pa)].toarray()  # pa among pose_all (both sorted)
        self.window.reset_to(pa, fa, P, bp, D, Ifa, i[fa].copy())


    def _eliminate_undoably(self, I: sp.csr_matrix | SummedRows, i: Array, pa: IntArray, mf: IntArray,
                            mp: IntArray) -> tuple[Array, Array]:
        """Eliminate features ``mf`` then poses ``mp`` from ``I x = i`` (CSR, ``(n, n)``)
        into two conditionals that can be undone (in part), as :meth:`_marginalise` would
        have: one feature batch (3x3 blocks, coupling to the poses as CSR) and one dense
        pose batch, its separator the active poses ``pa``. Returns the marginal ``P``
        ``(len(pa), len(pa))`` and ``bp`` of ``pa``. ``O(f + nnz + q^3)``, ``q = len(mp)``.

        Raises
        ------
        EstimatorError
            When two features share a measurement or a feature block is not positive
            definite.
        """
        ps = np.concatenate([pa, mp])
        na = len(pa)
        Spp = block(I, ps, ps).toarray()
        sv = i[ps].copy()
        if len(mf):
            F = len(mf) // FEATURE_DIM
            If = block(I, mf, np.concatenate([mf, ps]))  # the features' rows read once
            D = sparse_diagonal_blocks(If[:, : len(mf)])
            Dinv = inverse_spd_blocks(D)
            Bf = If[:, len(mf):]  # (3F, len(ps)), CSR as If is
            Dsp = block_diagonal_csr(Dinv)
            Spp -= (Bf.T @ (Dsp @ Bf)).toarray()
            sv -= Bf.T @ (Dsp @ i[mf])
            nz = np.zeros(len(ps), bool)
            nz[Bf.indices] = True
            self.conditionals.append(Conditional(mf, i[mf].copy(), Bf[:, np.flatnonzero(nz)], ps[nz], Dinv=Dinv, A=D))
            self.stats.marginalised_features += F
        Spp = 0.5 * (Spp + Spp.T)
        P, bp = Spp[:na, :na], sv[:na]
        if len(mp):
            A, C, bq = Spp[na:, na:], Spp[na:, :na], sv[na:]
            chol = pose_cholesky(A)
            Y = cho_solve(chol, np.column_stack([C, bq]), check_finite=False)
            P = P - C.T @ Y[:, :-1]
            bp = bp - C.T @ Y[:, -1]
            nz = np.flatnonzero(np.any(C != 0, axis=0))
            self.conditionals.append(Conditional(mp, bq.copy(), C[:, nz], pa[nz], chol=chol, A=A))
            self.stats.marginalised_poses += len(mp) // POSE_DIM
        return P, bp


__all__ = ["EntryMap", "IncrementalRecovery", "InformationListener", "RecoveryStats", "TrackedInformationStore"]
