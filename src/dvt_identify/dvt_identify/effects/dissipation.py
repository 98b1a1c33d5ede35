"""Dry frictions that add up to a friction: a model-level physics check (flagged, not refused:
:data:`dvt_identify.loop.UNDISSIPATIVE_NOTE`).

Each effect checks its own parameters (:meth:`~dvt_identify.effects.base.Effect.inadmissible`):
a Coulomb friction ``Fc >= 0`` with ``|offset| <= Fc``. Several effects on one member can
still add up to a friction that pushes the member: an ``unlisted`` term ``k sign(s) T(theta)``
(a friction that depends on where the member is: a screw's preload along its travel, a seal, a
ripple per revolution) lowers the member's dry friction where ``k T(theta) > 0``, and nothing
in either effect alone bounds the sum. A dry friction below 0 somewhere is a passive part that
drives the member from rest: not a physical instance of friction, whatever it does for the fit.

:func:`undissipative` sums the shares (:meth:`~dvt_identify.effects.base.Effect.dry_friction`)
of the effects on each member, in each direction, at every sample of the data (where the data
take the member) and names each member where the sum falls below 0: the direction, the
smallest value, the member's angle there and each effect's share. A member with a single
constant share is its effect's own check and is skipped here.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from dvt_identify.effects.base import Array, Effect, SegmentView
from dvt_identify.effects.position import Unlisted, member_motion

TOLERANCE = 1e-9
"""Relative round-off allowed below 0 (of the largest share's magnitude)."""


def undissipative(effects: Sequence[Effect], params: Sequence[Array], segments: Sequence[Any]
                  ) -> list[str]:
    """Why the dry frictions of ``effects`` (fitted ``params``, one array per effect) do not
    oppose the motion on ``segments`` (:class:`dvt_identify.data.Segment` or anything
    :meth:`SegmentView.of` takes), one text per member; empty when they do."""
    views = [SegmentView.of(seg) for seg in segments]
    groups: dict[tuple[float, ...], list[tuple[Effect, Array]]] = {}
    for eff, p in zip(effects, params, strict=True):
        if eff.member is None or not eff.params:
            continue
        key = tuple(float(v) for v in np.asarray(eff.member, float))
        groups.setdefault(key, []).append((eff, np.asarray(p, float)))
    return [why for members in groups.values()
            if (why := _member_violation(members, views)) is not None]


def _member_violation(members: Sequence[tuple[Effect, Array]],
                      views: Sequence[SegmentView]) -> str | None:
    """The violation text for one member's effects, or ``None``."""
    worst: tuple[float, int, float, list[str]] | None = None  # value, direction, angle, shares
    for view in views:
        n = view.u.shape[0]
        shares = [(e, sh) for e, p in members if (sh := e.dry_friction(p, view)) is not None]
        if not shares or (len(shares) == 1 and all(np.ndim(v) == 0 for v in shares[0][1])):
            continue  # nothing dry, or one constant share: the law's own check
        # each share as (effect, (positive (N,), negative (N,)))
        present: list[tuple[Effect, tuple[Array, Array]]] = [
            (e, (np.broadcast_to(np.asarray(sh[0], float), (n,)),
                 np.broadcast_to(np.asarray(sh[1], float), (n,)))) for e, sh in shares]
        scale = max(float(np.max(np.abs(a))) for _, dirs in present for a in dirs)
        for d in (0, 1):
            total = np.sum([dirs[d] for _, dirs in present], axis=0)
            i = int(np.argmin(total))
            low = float(total[i])
            if low >= -TOLERANCE * max(scale, 1e-12) or (worst is not None and low >= worst[0]):
                continue
            eff0 = present[0][0]
            angle = float(member_motion(view, eff0.require_member(), eff0.readout)[1][i])
            parts = [f"{e.label().split(':')[0]} {float(dirs[d][i]):+.4g}"
                     for e, dirs in present]
            worst = (low, d, angle, parts)
    if worst is None:
        return None
    low, d, angle, parts = worst
    eff0 = members[0][0]
    unit = eff0.units[0] if isinstance(eff0, Unlisted) else eff0.params[0].unit
    return (f"the dry friction on {eff0.where} in the {'positive' if d == 0 else 'negative'} "
            f"direction falls to {low:.4g}{' ' + unit if unit else ''} at its angle "
            f"{angle:.4g} ({', '.join(parts)}): the dry frictions of a member must add up to "
            "a friction that opposes its motion everywhere the data take it, not one that "
            "drives it from rest")
