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

Force laws [N m] acting against the member's motion: Coulomb ``Fc tanh(v/eps) + offset``,
Stribeck ``Fs exp(-(v/vs)^2) tanh(v/eps)``, windage ``Cw |v| v``, viscous ``b v``; the generalised
torque is ``-member * law(v)``. ``eps`` (default 0.5 rad/s) smooths the sign for a stable
sample-rate simulation. ``delay`` shifts the predicted outputs by whole samples, ``gain`` scales
output ``output`` by ``1 + gain``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_model.errors import ModelError

Array = NDArray[np.float64]
_FORCE_KEYS = {"coulomb": ("Fc",), "stribeck": ("Fs", "vs"), "windage": ("Cw",),
               "viscous": ("b",)}


@dataclass(frozen=True)
class Terms:
    """Parsed effect terms: force terms and output transforms."""

    forces: tuple[tuple[str, Array, dict[str, float]], ...] = ()
    delay: float = 0.0
    gains: tuple[float, float] = (0.0, 0.0)
    eps: float = 0.5

    def extra_force(self, omega: Array, t: float) -> Array:
        """Generalised torque of all force terms [N m], shape (2,)."""
        f = np.zeros(2)
        for kind, member, p in self.forces:
            v = float(member @ omega)
            s = math.tanh(v / self.eps)
            if kind == "coulomb":
                law = p["Fc"] * s + p.get("offset", 0.0)
            elif kind == "stribeck":
                law = p["Fs"] * math.exp(-((v / p["vs"]) ** 2)) * s
            elif kind == "windage":
                law = p["Cw"] * abs(v) * v
            else:
                law = p["b"] * v
            f -= member * law
        return f

    @property
    def empty(self) -> bool:
        return not self.forces and self.delay == 0.0 and self.gains == (0.0, 0.0)


def _num(entry: dict[str, Any], key: str, where: str) -> float:
    value = entry.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ModelError(f"{where}.{key}: expected a finite number, got {value!r}")
    return float(value)


def parse_terms(text: str | Sequence[dict[str, Any]]) -> Terms:
    """Parse the JSON list (or an already-decoded list); '' or '[]' gives no terms.

    Raises:
        ModelError: naming the entry index and key.
    """
    if isinstance(text, str):
        if not text.strip():
            return Terms()
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelError(f"effects: not valid JSON: {exc}") from exc
    else:
        data = list(text)
    if not isinstance(data, list):
        raise ModelError(f"effects: expected a JSON list, got {type(data).__name__}")
    forces: list[tuple[str, Array, dict[str, float]]] = []
    delay = 0.0
    gains = [0.0, 0.0]
    eps = 0.5
    for i, entry in enumerate(data):
        where = f"effects[{i}]"
        if not isinstance(entry, dict):
            raise ModelError(f"{where}: expected an object, got {entry!r}")
        kind = entry.get("kind")
        if kind in _FORCE_KEYS:
            member = np.asarray(entry.get("member"), dtype=float)
            if member.shape != (2,) or not np.all(np.isfinite(member)):
                raise ModelError(f"{where}.member: expected 2 finite numbers, got "
                                 f"{entry.get('member')!r}")
            p = {k: _num(entry, k, where) for k in _FORCE_KEYS[kind]}
            if kind == "coulomb" and "offset" in entry:
                p["offset"] = _num(entry, "offset", where)
            if kind == "stribeck" and p["vs"] <= 0.0:
                raise ModelError(f"{where}.vs: expected > 0, got {p['vs']!r}")
            forces.append((str(kind), member, p))
            if "eps" in entry:
                eps = _num(entry, "eps", where)
        elif kind == "delay":
            delay = _num(entry, "seconds", where)
            if not 0.0 <= delay <= 1.0:
                raise ModelError(f"{where}.seconds: expected 0..1 s, got {delay!r}")
        elif kind == "gain":
            out = entry.get("output")
            if out not in (0, 1):
                raise ModelError(f"{where}.output: expected 0 or 1, got {out!r}")
            gains[int(out)] = _num(entry, "gain", where)
        else:
            raise ModelError(f"{where}.kind: expected one of {sorted(_FORCE_KEYS)} + "
                             f"['delay', 'gain'], got {kind!r}")
    return Terms(forces=tuple(forces), delay=delay, gains=(gains[0], gains[1]), eps=eps)
