"""Identified effect terms the live model can carry (pure; JSON-serialisable).

The identifier (``dvt_identify``) pushes accepted effects to the model node as a JSON list; each
entry is a generalised-force term on one member (speed ``v = member . omega``) or an output
transform::

    [{"kind": "coulomb",  "member": [a, b], "Fc": 0.3, "offset": 0.0},
     {"kind": "stribeck", "member": [a, b], "Fs": 0.2, "vs": 5.0},
     {"kind": "windage",  "member": [a, b], "Cw": 1e-5},
     {"kind": "viscous",  "member": [a, b], "b": 1e-3},
     {"kind": "delay",    "seconds": 0.004},
     {"kind": "gain",     "output": 0, "gain": 0.02}]

The schema and its physical admissibility (e.g. ``Fc >= 0``, ``b >= 0``, ``gain > -0.5``, at
most :data:`~dvt_model.contract.MAX_EFFECT_TERMS` terms) are the contract's
(:data:`dvt_model.contract.EFFECT_TERMS`, :func:`~dvt_model.contract.validate_effects`); the
force laws [N m] are :mod:`dvt_model.friction`'s, each acting against the member's motion: the
generalised torque is ``-member * F(v)``. ``eps`` (default 0.5 rad/s, per term) smooths the
sign for a stable sample-rate simulation. ``delay`` shifts the predicted outputs by whole
samples, ``gain`` scales output ``output`` by ``1 + gain``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_model import friction
from dvt_model.contract import SPEED_NAMES, validate_effects

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ForceTerm:
    """One force term: its kind, member form (2,) and law parameters (contract field names)."""

    kind: str
    member: Array
    params: dict[str, float]

    def law(self, v: float) -> float:
        """The resisting force F(v) [N m] at member speed ``v`` [rad/s]."""
        p = self.params
        if self.kind == "coulomb":
            return float(friction.coulomb(v, p["Fc"], p["offset"], p["eps"]))
        if self.kind == "stribeck":
            return float(friction.stribeck(v, p["Fs"], p["vs"], p["eps"]))
        if self.kind == "windage":
            return float(friction.windage(v, p["Cw"]))
        return float(friction.viscous(v, p["b"]))


@dataclass(frozen=True)
class Terms:
    """Parsed effect terms: force terms and output transforms.

    Attributes:
        forces: the force terms, in the order given.
        delay: output delay [s].
        gains: relative output gain error per output (output scaled by ``1 + gain``).
    """

    forces: tuple[ForceTerm, ...] = ()
    delay: float = 0.0
    gains: tuple[float, float] = (0.0, 0.0)

    def extra_force(self, omega: Array, t: float) -> Array:
        """Generalised torque of all force terms [N m], shape (2,), at speeds ``omega`` (2,)."""
        f = np.zeros(2)
        for term in self.forces:
            f -= term.member * term.law(float(term.member @ omega))
        return f

    @property
    def empty(self) -> bool:
        return not self.forces and self.delay == 0.0 and self.gains == (0.0, 0.0)


def parse_terms(text: str | Sequence[Any] | None) -> Terms:
    """Parse the ``effects`` JSON list (or an already-decoded list); '', '[]', None: no terms.

    Raises:
        ContractError: from :func:`dvt_model.contract.validate_effects`, naming the entry
            index, the field, the value and what is admissible.
    """
    forces: list[ForceTerm] = []
    delay = 0.0
    gains = [0.0, 0.0]
    for term in validate_effects(text, n_outputs=len(SPEED_NAMES)):
        kind = term["kind"]
        if kind == "delay":
            delay = float(term["seconds"])
        elif kind == "gain":
            gains[int(term["output"])] = float(term["gain"])
        else:
            params = {k: float(v) for k, v in term.items() if k not in ("kind", "member")}
            forces.append(ForceTerm(kind, np.asarray(term["member"], dtype=float), params))
    return Terms(forces=tuple(forces), delay=delay, gains=(gains[0], gains[1]))
