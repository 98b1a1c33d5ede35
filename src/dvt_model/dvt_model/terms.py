"""Identified effect terms the live model can carry (pure; JSON-serialisable).

The identifier (``dvt_identify``) pushes accepted effects to the model node as a JSON list; each
entry is a generalised-force term on one member (speed ``v = member . omega``; the angle terms'
angle ``theta_a = angle . theta``, the optional field ``angle`` defaulting to ``member``) or an
output transform::

    [{"kind": "coulomb",  "member": [a, b], "Fc": 0.3, "offset": 0.0},
     {"kind": "stribeck", "member": [a, b], "Fs": 0.2, "vs": 5.0},
     {"kind": "windage",  "member": [a, b], "Cw": 1e-5},
     {"kind": "viscous",  "member": [a, b], "b": 1e-3},
     {"kind": "gravity",  "member": [0, 1], "a": 0.4, "b": -0.1, "reduction": 20.0},
     {"kind": "angle_periodic", "member": [1, 0], "a": 0.02, "b": 0.01, "order": 16},
     {"kind": "angle_periodic", "member": [1, 0], "angle": [1.49, -0.49], "a": 0.02,
      "b": 0.0, "order": 16},
     {"kind": "library",  "member": [0, 1], "k": 0.05, "speed": "sign", "trig": "cos",
      "order": 1, "input": "drive_motor"},
     {"kind": "library",  "member": [1, 0], "k": -0.002, "input": "drive_motor",
      "input_power": "abs_sq"},
     {"kind": "delay",    "seconds": 0.004},
     {"kind": "gain",     "output": 0, "gain": 0.02}]

The schema and its physical admissibility (e.g. ``Fc >= 0``, ``b >= 0``, ``gain > -0.5``,
``reduction > 0``, ``order >= 0``, the ``library`` term's ``speed`` in ``'', sign, abs_sq,
cube, lin, abs``, ``trig`` in ``'', cos, sin``, ``input`` in ``'', drive_motor, brake1, brake2,
brake3``, ``input_power`` in ``'', abs_sq, cube``; at most
:data:`~dvt_model.contract.MAX_EFFECT_TERMS` terms) are the contract's
(:data:`dvt_model.contract.EFFECT_TERMS`, :func:`~dvt_model.contract.validate_effects`).

Speed-dependent terms (:class:`ForceTerm`, :meth:`Terms.extra_force`): the force laws [N m] are
:mod:`dvt_model.laws`' (the term's ``kind`` names the law in
:data:`~dvt_model.laws.LAWS`), each acting against the member's motion: the generalised torque is
``-member * F(v)``. ``eps`` (default 0.5 rad/s, per term) smooths the sign for a stable
sample-rate simulation.

Angle-dependent terms (:class:`AngleTerms`, :meth:`Terms.angle_force`) are torques *on* the
member, generalised torque ``+member * tau`` (the sign of the identifier's exogenous member
forces, so an identified ``a`` is pushed unchanged):

- ``gravity``: ``tau = a cos(theta_a / reduction) + b sin(theta_a / reduction)``;
- ``angle_periodic``: ``tau = a cos(order theta_a) + b sin(order theta_a)`` (e.g. a mesh ripple
  on the sun shaft with ``angle`` the sun's angle relative to its carrier);
- ``library``: ``tau = k S(v) T(order theta_a) P(u)`` with ``S`` 1, ``tanh(v / eps)``,
  ``|v| v``, ``v^3``, ``v`` or ``|v|``, ``T`` 1, ``cos`` or ``sin`` (``order`` ignored without
  one), ``P(u)`` 1 or the named current ``u`` [A] (the inputs held over the step: drive motor,
  brakes 1-3), ``|u| u`` or ``u^3`` (``input_power``; an actuator map: a torque constant that
  saturates, a gain that depends on speed or angle).

Held over a simulation step of length ``dt`` the trigonometric factors are their means over the
angle interval ``[theta_a, theta_a + (angle . omega) dt]`` (``dt = 0``: the point values), as
the identifier's are over the measured interval: a mesh ripple faster than the step does not
alias. The phase
is that of the model's angles, anchored to the measured positions when the driver publishes
them; without positions the angles start at 0 at every anchor and the phase is arbitrary.

``delay`` shifts the predicted outputs by whole samples, ``gain`` scales output ``output`` by
``1 + gain``.

Lost motion (:mod:`dvt_model.backlash`): ``dead_zone`` takes ``u - clip(u, -delta, delta)`` of
the named current before the model sees it (:attr:`Terms.dead_zones`); ``play`` and
``spline_play`` map the predicted speed of output ``output`` to what its sensor reads
(:meth:`Terms.output_maps`: :class:`~dvt_model.backlash.OutputPlay`,
:class:`~dvt_model.backlash.OutputSpline`), before the delay and the gain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_model.backlash import OutputMap, OutputPlay, OutputSpline
from dvt_model.contract import (
    ANGLE_TERM_KINDS,
    CURRENT_NAMES,
    OUTPUT_PLAY_KINDS,
    SPEED_NAMES,
    validate_effects,
)
from dvt_model.laws import LAWS

Array = NDArray[np.float64]
Vec = Array | Sequence[float]
"""A short vector: a float array or a sequence of numbers."""

N_INPUTS = len(CURRENT_NAMES)
"""Inputs a ``library`` term can name: drive-motor current and brake currents 1-3 [A]."""
_SMALL_PHASE = 1e-6
"""Below this phase change over a step [rad] the step mean of cos/sin is the endpoint mean."""


@dataclass(frozen=True)
class ForceTerm:
    """One force term: its kind, member form (2,) and law parameters (contract field names)."""

    kind: str
    member: Array
    params: dict[str, float]

    def law(self, v: float) -> float:
        """The resisting force F(v) [N m] at member speed ``v`` [rad/s]."""
        return float(LAWS[self.kind](v, self.params))


_SPEED_CODES = {"": 0, "sign": 1, "abs_sq": 2, "cube": 3, "lin": 4, "abs": 5}
_POWER_CODES = {"": 1, "abs_sq": 2, "cube": 3}


@dataclass(frozen=True)
class AngleTerms:
    """The angle-dependent terms as arrays, one row per elementary term
    ``tau_j = (A_j Tc_j + B_j Ts_j) S_j(v_j) P_j(u_j)`` with ``Tc``/``Ts`` the (step-mean)
    cosine and sine of ``freq_j theta_j``: a ``gravity`` term is ``(a, b, 1 / reduction)``, an
    ``angle_periodic`` one ``(a, b, order)``, a ``library`` one ``(k, 0, order)`` for ``cos``
    and for no angle factor (``order`` 0), ``(0, k, order)`` for ``sin``.

    Attributes:
        member: member forms (the torque's member, the speed factor's speed), shape (n, 2).
        angle: angle forms (the trigonometric factors' angle), shape (n, 2).
        freq: angle frequency per radian of the angle, shape (n,).
        a, b: cosine and sine coefficients [N m per unit of the other factors], shape (n,).
        speed: speed factor code (0 none, 1 ``tanh(v / eps)``, 2 ``|v| v``, 3 ``v^3``, 4 ``v``,
            5 ``|v|``), shape (n,).
        eps: sign smoothing speed [rad/s], shape (n,).
        input: input index (0 drive motor, 1-3 brakes; :data:`N_INPUTS`: none), shape (n,).
        power: the input's power code (1 ``u``, 2 ``|u| u``, 3 ``u^3``), shape (n,).
        kinds: the contract kind of each row.
    """

    member: Array
    angle: Array
    freq: Array
    a: Array
    b: Array
    speed: NDArray[np.int64]
    eps: Array
    input: NDArray[np.int64]
    power: NDArray[np.int64]
    kinds: tuple[str, ...] = ()
    _rows: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # plain floats per row: a Python loop over a few terms with math.* is several times
        # faster than the numpy expression on arrays this small (the node steps at 1 kHz)
        rows = tuple(
            (float(m[0]), float(m[1]), float(g[0]), float(g[1]), float(fr), float(a), float(b),
             float(sp), float(e), float(i), float(pw))
            for m, g, fr, a, b, sp, e, i, pw in zip(self.member, self.angle, self.freq, self.a,
                                                    self.b, self.speed, self.eps, self.input,
                                                    self.power, strict=True))
        object.__setattr__(self, "_rows", rows)

    @classmethod
    def from_terms(cls, terms: Sequence[dict[str, Any]]) -> AngleTerms:
        """Rows from validated ``gravity``/``angle_periodic``/``library`` terms."""
        rows: list[tuple[float, float, float, int, float, int, int]] = []
        for t in terms:
            kind = t["kind"]
            if kind == "gravity":
                rows.append((1.0 / float(t["reduction"]), float(t["a"]), float(t["b"]), 0, 1.0,
                             N_INPUTS, 1))
            elif kind == "angle_periodic":
                rows.append((float(t["order"]), float(t["a"]), float(t["b"]), 0, 1.0,
                             N_INPUTS, 1))
            else:  # library
                trig = t["trig"]
                k = float(t["k"])
                order = float(t["order"]) if trig else 0.0
                inp = CURRENT_NAMES.index(t["input"]) if t["input"] else N_INPUTS
                rows.append((order, 0.0 if trig == "sin" else k, k if trig == "sin" else 0.0,
                             _SPEED_CODES[t["speed"]], float(t["eps"]), inp,
                             _POWER_CODES[t.get("input_power", "")]))
        n = len(rows)
        return cls(member=np.array([t["member"] for t in terms], dtype=float).reshape(n, 2),
                   angle=np.array([t.get("angle", t["member"]) for t in terms],
                                  dtype=float).reshape(n, 2),
                   freq=np.array([r[0] for r in rows], dtype=float),
                   a=np.array([r[1] for r in rows], dtype=float),
                   b=np.array([r[2] for r in rows], dtype=float),
                   speed=np.array([r[3] for r in rows], dtype=np.int64),
                   eps=np.array([r[4] for r in rows], dtype=float),
                   input=np.array([r[5] for r in rows], dtype=np.int64),
                   power=np.array([r[6] for r in rows], dtype=np.int64),
                   kinds=tuple(str(t["kind"]) for t in terms))

    def __len__(self) -> int:
        return int(self.freq.shape[0])

    def torques(self, theta: Vec, omega: Vec, u: Vec | None = None,
                dt: float = 0.0) -> Array:
        """Each row's torque on its member [N m], shape (n,).

        Args:
            theta: angles (theta_sun, theta_carrier3) [rad], shape (2,).
            omega: speeds [rad/s], shape (2,).
            u: inputs (drive-motor current, brake currents 1-3) [A], shape (4,); ``None``:
                zero (a term with an input factor then gives 0).
            dt: the step over which the torque is held [s]; 0: the point value.
        """
        return np.asarray(self._evaluate(theta, omega, u, dt)[0])

    def force(self, theta: Vec, omega: Vec, u: Vec | None = None,
              dt: float = 0.0) -> Array:
        """Generalised torque of all rows [N m], shape (2,) (``sum_j member_j tau_j``); the
        arguments as :meth:`torques`."""
        return np.array(self._evaluate(theta, omega, u, dt)[1])

    def _evaluate(self, theta: Vec, omega: Vec, u: Vec | None, dt: float
                  ) -> tuple[list[float], tuple[float, float]]:
        """Row torques and their generalised torque (see :meth:`torques`)."""
        t0, t1 = float(theta[0]), float(theta[1])
        w0, w1 = float(omega[0]), float(omega[1])
        uu = (0.0,) * N_INPUTS if u is None else tuple(float(x) for x in u)
        cos, sin = math.cos, math.sin
        taus: list[float] = []
        f0 = f1 = 0.0
        for m0, m1, g0, g1, fr, a, b, sp, eps, inp, pw in self._rows:
            if fr == 0.0:
                tau = a  # cos(0) = 1, sin(0) = 0
            else:
                ph = fr * (g0 * t0 + g1 * t1)
                d = fr * (g0 * w0 + g1 * w1) * dt
                if d == 0.0:
                    tau = a * cos(ph) + b * sin(ph)
                elif abs(d) < _SMALL_PHASE:
                    tau = 0.5 * (a * (cos(ph) + cos(ph + d)) + b * (sin(ph) + sin(ph + d)))
                else:
                    c0, s0, c1, s1 = cos(ph), sin(ph), cos(ph + d), sin(ph + d)
                    tau = (a * (s1 - s0) + b * (c0 - c1)) / d
            if sp:
                v = m0 * w0 + m1 * w1
                tau *= (math.tanh(v / eps) if sp == 1.0 else abs(v) * v if sp == 2.0
                        else v * v * v if sp == 3.0 else v if sp == 4.0 else abs(v))
            if inp < N_INPUTS:
                x = uu[int(inp)]
                tau *= x if pw == 1.0 else (abs(x) * x if pw == 2.0 else x * x * x)
            taus.append(tau)
            f0 += m0 * tau
            f1 += m1 * tau
        return taus, (f0, f1)


_NO_ANGLE_TERMS = AngleTerms.from_terms([])


@dataclass(frozen=True)
class Terms:
    """Parsed effect terms: force terms, angle-dependent terms and output transforms.

    Attributes:
        forces: the speed-dependent force terms, in the order given.
        delay: output delay [s].
        gains: relative output gain error per output (output scaled by ``1 + gain``).
        angle_terms: the angle-dependent terms (``gravity``, ``angle_periodic``, ``library``).
        dead_zones: half-width of the dead zone on each current (drive motor, brakes 1-3) [A],
            0 for none.
        plays: the ``play``/``spline_play`` term of each output (validated fields), or
            ``None``.
    """

    forces: tuple[ForceTerm, ...] = ()
    delay: float = 0.0
    gains: tuple[float, float] = (0.0, 0.0)
    angle_terms: AngleTerms = _NO_ANGLE_TERMS
    dead_zones: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    plays: tuple[dict[str, Any] | None, dict[str, Any] | None] = (None, None)

    def output_maps(self) -> tuple[OutputMap | None, OutputMap | None]:
        """A fresh sensor map (state inside) for each output with a ``play`` or
        ``spline_play`` term, else ``None``."""
        return (_output_map(self.plays[0]), _output_map(self.plays[1]))

    def extra_force(self, omega: Array, t: float) -> Array:
        """Generalised torque of all force terms [N m], shape (2,), at speeds ``omega`` (2,)."""
        f = np.zeros(2)
        for term in self.forces:
            f -= term.member * term.law(float(term.member @ omega))
        return f

    def angle_force(self, theta: Vec, omega: Vec, t: float = 0.0,
                    u: Vec | None = None, dt: float = 0.0) -> Array:
        """Generalised torque of the angle-dependent terms [N m], shape (2,).

        The signature of :data:`dvt_model.hybrid.AngleInputForce`.

        Args:
            theta: angles (theta_sun, theta_carrier3) [rad], shape (2,).
            omega: speeds [rad/s], shape (2,).
            t: time [s] (unused: no term is clocked on time).
            u: inputs (drive-motor current, brake currents 1-3) [A], shape (4,), or ``None``
                (zero).
            dt: the step over which the torque is held [s] (angle factors averaged over it);
                0: the point value.
        """
        if not len(self.angle_terms):
            return np.zeros(2)
        return self.angle_terms.force(theta, omega, u, dt)

    @property
    def has_angle_terms(self) -> bool:
        """Whether any angle-dependent term is present."""
        return len(self.angle_terms) > 0

    @property
    def has_lost_motion(self) -> bool:
        """Whether any ``dead_zone``, ``play`` or ``spline_play`` term is present."""
        return any(self.dead_zones) or any(p is not None for p in self.plays)

    @property
    def empty(self) -> bool:
        return (not self.forces and not self.has_angle_terms and self.delay == 0.0
                and self.gains == (0.0, 0.0) and not self.has_lost_motion)


def _output_map(term: dict[str, Any] | None) -> OutputMap | None:
    """The stateful sensor map of a validated ``play``/``spline_play`` term."""
    if term is None:
        return None
    if term["kind"] == "play":
        return OutputPlay(delta=float(term["delta"]))
    return OutputSpline(gap=float(term["gap"]), wn=float(term["wn"]), zeta=float(term["zeta"]))


def parse_terms(text: str | Sequence[Any] | None) -> Terms:
    """Parse the ``effects`` JSON list (or an already-decoded list); '', '[]', None: no terms.

    Raises:
        ContractError: from :func:`dvt_model.contract.validate_effects`, naming the entry
            index, the field, the value and what is admissible.
    """
    forces: list[ForceTerm] = []
    angle: list[dict[str, Any]] = []
    delay = 0.0
    gains = [0.0, 0.0]
    zones = [0.0] * N_INPUTS
    plays: list[dict[str, Any] | None] = [None, None]
    for term in validate_effects(text, n_outputs=len(SPEED_NAMES)):
        kind = term["kind"]
        if kind == "delay":
            delay = float(term["seconds"])
        elif kind == "gain":
            gains[int(term["output"])] = float(term["gain"])
        elif kind == "dead_zone":
            zones[CURRENT_NAMES.index(term["input"])] = float(term["delta"])
        elif kind in OUTPUT_PLAY_KINDS:
            plays[int(term["output"])] = term
        elif kind in ANGLE_TERM_KINDS:
            angle.append(term)
        else:
            params = {k: float(v) for k, v in term.items() if k not in ("kind", "member")}
            forces.append(ForceTerm(kind, np.asarray(term["member"], dtype=float), params))
    return Terms(forces=tuple(forces), delay=delay, gains=(gains[0], gains[1]),
                 angle_terms=AngleTerms.from_terms(angle) if angle else _NO_ANGLE_TERMS,
                 dead_zones=(zones[0], zones[1], zones[2], zones[3]),
                 plays=(plays[0], plays[1]))
