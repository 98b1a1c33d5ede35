"""Pairing the messages of one controller sample by stamp: written once, used offline and live.

The contract: the two messages of one sample (``/dvt/joint_states``, ``/dvt/currents``) carry
the identical ``header.stamp``. Offline (:func:`pair_stamps`) the streams are matched by
identical stamps, or, for recordings from other loggers whose topics are stamped separately,
by nearest stamp within a fraction of the sample period. Live (:class:`LivePairer`) messages
are matched by identical stamp as they arrive, with a bounded number waiting for a partner.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from dvt_model.errors import BagError

Int1D = NDArray[np.int64]
T = TypeVar("T")

IDENTICAL_SHARE = 0.99
"""If at least this share of the shorter stream has identical stamps, pairing is exact."""
NEAREST_TOLERANCE = 0.25
"""Nearest-stamp pairing accepts a partner within this fraction of the median sample period."""
MIN_PAIRED_SHARE = 0.5
"""Nearest-stamp pairing fails if fewer than this share of the reference's samples pair."""


@dataclass(frozen=True)
class Pairing:
    """Indices into each topic's messages of the paired samples, in stamp order.

    ``index[topic][k]`` is the message of ``topic`` in sample ``k``; ``unmatched[topic]`` counts
    that topic's messages left without a partner; ``exact`` says whether stamps were identical.
    """

    index: dict[str, Int1D]
    unmatched: dict[str, int]
    exact: bool

    @property
    def n(self) -> int:
        return int(next(iter(self.index.values())).size) if self.index else 0


def pair_stamps(stamps: Mapping[str, Int1D], reference: str, *, where: str = "recording",
                exact_only: bool = False) -> Pairing:
    """Pair the messages of several topics by stamp [ns] (each array strictly increasing).

    Args:
        stamps: per topic, the message stamps [ns], shape (n_topic,).
        reference: the topic whose samples define the time base.
        where: the bag path (or other source) named in errors.
        exact_only: only identical stamps pair (the contract's rule); else fall back to the
            nearest stamp within :data:`NEAREST_TOLERANCE` of a sample period.

    Raises:
        BagError: no (or, for nearest pairing, too few) samples pair; names ``where`` and the
            topics.
    """
    if reference not in stamps:
        raise BagError(f"{where}: reference topic {reference} not among {sorted(stamps)}")
    arrays = {t: np.asarray(s, dtype=np.int64).reshape(-1) for t, s in stamps.items()}
    common = arrays[reference]
    for s in arrays.values():
        common = np.intersect1d(common, s, assume_unique=True)
    shortest = min(s.size for s in arrays.values())
    others = [t for t in arrays if t != reference]
    if exact_only or common.size >= IDENTICAL_SHARE * shortest:
        if common.size == 0:
            raise BagError(f"{where}: topics {reference} and {', '.join(others)} share no "
                           "header.stamp; the contract requires the messages of one sample to "
                           "carry the identical stamp")
        index = {t: np.searchsorted(s, common).astype(np.int64) for t, s in arrays.items()}
        return Pairing(index=index, unmatched={t: int(s.size - common.size)
                                               for t, s in arrays.items()}, exact=True)
    ref = arrays[reference]
    dt = float(np.median(np.diff(ref))) if ref.size > 1 else 1.0
    keep = np.ones(ref.size, dtype=bool)
    best_of: dict[str, Int1D] = {}
    for topic, s in arrays.items():
        if s.size == 0:
            keep[:] = False
            best_of[topic] = np.zeros(ref.size, dtype=np.int64)
            continue
        j = np.clip(np.searchsorted(s, ref), 1, max(s.size - 1, 1))
        left = np.abs(ref - s[j - 1])
        right = np.abs(s[np.minimum(j, s.size - 1)] - ref)
        best = np.where(left <= right, j - 1, np.minimum(j, s.size - 1)).astype(np.int64)
        keep &= np.abs(s[best] - ref) <= dt * NEAREST_TOLERANCE
        best_of[topic] = best
    if keep.sum() < MIN_PAIRED_SHARE * ref.size or not keep.any():
        raise BagError(f"{where}: topics {reference} and {', '.join(others)}: fewer than "
                       f"{MIN_PAIRED_SHARE:.0%} of the samples share a stamp (within "
                       f"{NEAREST_TOLERANCE:g} of a sample period); cannot pair them")
    index = {t: b[keep] for t, b in best_of.items()}
    return Pairing(index=index, unmatched={t: int(arrays[t].size - int(keep.sum()))
                                           for t in arrays}, exact=False)


@dataclass
class LivePairer(Generic[T]):
    """Pairs live messages of ``slots`` streams by identical stamp [ns].

    :meth:`add` returns the complete tuple (one message per slot) when the last partner
    arrives, else ``None``. At most ``max_pending`` incomplete samples wait; beyond that the
    oldest is dropped and counted in :attr:`unpaired`.
    """

    slots: int = 2
    max_pending: int = 2000
    unpaired: int = 0
    _pending: dict[int, list[T | None]] = field(default_factory=dict)

    def add(self, stamp_ns: int, slot: int, msg: T) -> tuple[T, ...] | None:
        """Add ``msg`` of stream ``slot`` (0-based) stamped ``stamp_ns``."""
        if not 0 <= slot < self.slots:
            raise ValueError(f"slot: expected 0..{self.slots - 1}, got {slot!r}")
        entry = self._pending.pop(stamp_ns, None)
        if entry is None:
            entry = [None] * self.slots
        entry[slot] = msg
        for m in entry:  # a plain loop: no generator per message at 1 kHz
            if m is None:
                break
        else:
            return tuple(entry)  # type: ignore[arg-type]  # every slot is filled
        self._pending[stamp_ns] = entry
        while len(self._pending) > self.max_pending:
            del self._pending[min(self._pending)]
            self.unpaired += 1
        return None

    @property
    def pending(self) -> int:
        return len(self._pending)


def paired_topics(topics: Sequence[str]) -> tuple[str, ...]:
    """The distinct topics of ``topics`` in first-seen order (the pairing's slot order)."""
    return tuple(dict.fromkeys(topics))
