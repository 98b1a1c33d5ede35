"""The speed laws of the suite, written once, in one table (pure; numpy; compilable with numba).

Each law is one function of the member speed ``v`` [rad/s, or the member's speed unit] and its
parameters returning the *resisting* force ``F(v)`` [N m, or the member's force unit]; the
generalised force on the member is ``-F(v)``. They work on scalars and on numpy arrays alike.
The dry laws share one smoothed sign, :func:`sign_eps`: ``tanh(v / eps)`` for ``eps > 0`` (a
stable law for a fixed-step simulation, what the plant and the model node use), the exact
``sign(v)`` for ``eps == 0`` (the identifier's stick rule).

Who calls them:

- the model node: :class:`dvt_model.terms.ForceTerm` evaluates a pushed term by its ``kind``
  through :data:`LAWS` (the term's fields are :attr:`Law.params`; the contract's
  :data:`~dvt_model.contract.EFFECT_TERMS` entry of each law is built from them);
- the plant: :class:`dvt_driver.plant.physics.FrictionForces` (Coulomb, Stribeck, windage) and
  the position-dependent friction bump (:func:`coulomb`);
- the identifier: :mod:`dvt_identify.simloop` compiles :func:`coded_value` and
  :func:`coded_partials` (and through them every law and :func:`sign_eps`) with numba: a law in
  a compiled kernel is an integer :attr:`Law.code` with three numbers ``(p0, p1, p2)``
  (:attr:`Law.coded`), and these two functions dispatch on the code. This module does not
  import numba; the identifier registers the functions of :data:`JITABLE` as jitable
  (``numba.extending.register_jitable``) before it compiles its kernels, so a compiled law is
  this source, unchanged.

Adding a law (``docs/effects.md``): its function and its ``*_partials`` here, one :class:`Law`
entry in :data:`LAWS`, one branch in :func:`coded_value` and :func:`coded_partials`. The
identifier drops its cached kernels when this file changes (``simloop._drop_stale_cache``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

# ---------------------------------------------------------------------------------------------
# the laws (resisting force F(v)); each is numba-compilable once its callees are jitable


def sign_eps(v: Any, eps: float) -> Any:
    """The smoothed sign: ``tanh(v / eps)`` for ``eps > 0``, else ``sign(v)`` (0 at v = 0)."""
    if eps > 0.0:
        return np.tanh(v / eps)
    return np.sign(v)


def coulomb(v: Any, fc: Any, offset: Any, eps: float) -> Any:
    """Dry (Coulomb) friction ``Fc sign_eps(v) + offset``; ``Fc >= 0``."""
    return fc * sign_eps(v, eps) + offset


def stribeck(v: Any, fs: Any, vs: Any, eps: float, delta: Any = 2.0) -> Any:
    """Stribeck excess ``Fs exp(-|v/vs|^delta) sign_eps(v)``; ``Fs >= 0``, ``vs > 0``."""
    return fs * np.exp(-np.abs(v / vs) ** delta) * sign_eps(v, eps)


def windage(v: Any, cw: Any) -> Any:
    """Quadratic drag ``Cw |v| v``; ``Cw >= 0``."""
    return cw * np.abs(v) * v


def viscous(v: Any, b: Any) -> Any:
    """Viscous drag ``b v``; ``b >= 0``."""
    return b * v


def abs_viscous(v: Any, dfv: Any) -> Any:
    """Direction-dependent part of viscous friction ``dFv |v|`` (``Fv+ = Fv + dFv``)."""
    return dfv * np.abs(v)


# ---------------------------------------------------------------------------------------------
# their exact partial derivatives in the coded parameters (the identifier's sensitivities and
# the implicit hold of a smoothed sign): (F, dF/dv, dF/dp0, dF/dp1, dF/dp2), scalars


def _sgn(v: float) -> float:
    """``sign(v)`` of a float as a float (0 at 0)."""
    return 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)


def coulomb_partials(v: float, fc: float, eps: float
                     ) -> tuple[float, float, float, float, float]:
    """``F = Fc sign_eps(v)`` (coded ``(Fc, eps, -)``, no offset) and its partials."""
    if eps > 0.0:
        t = np.tanh(v / eps)
        q = 1.0 - t * t
        return fc * t, fc * q / eps, t, -fc * q * v / (eps * eps), 0.0
    sg = _sgn(v)
    return fc * sg, 0.0, sg, 0.0, 0.0


def stribeck_partials(v: float, fs: float, vs: float, eps: float
                      ) -> tuple[float, float, float, float, float]:
    """``F = Fs exp(-(v/vs)^2) sign_eps(v)`` (coded ``(Fs, vs, eps)``) and its partials (0 at
    ``v = 0`` for the exact sign, where the law is 0 for every parameter)."""
    if eps > 0.0:
        e = np.exp(-(v / vs) ** 2)
        t = np.tanh(v / eps)
        q = 1.0 - t * t
        return (fs * e * t, fs * e * (q / eps - 2.0 * v / (vs * vs) * t), e * t,
                fs * t * e * 2.0 * v * v / (vs * vs * vs), -fs * e * q * v / (eps * eps))
    if v == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    sg = 1.0 if v > 0.0 else -1.0
    e = np.exp(-(v / vs) ** 2)
    return (fs * e * sg, -2.0 * fs * abs(v) * e / (vs * vs), e * sg,
            fs * sg * e * 2.0 * v * v / (vs * vs * vs), 0.0)


def windage_partials(v: float, cw: float) -> tuple[float, float, float, float, float]:
    """``F = Cw |v| v`` (coded ``(Cw, -, -)``) and its partials."""
    return cw * abs(v) * v, 2.0 * cw * abs(v), v * abs(v), 0.0, 0.0


def abs_viscous_partials(v: float, dfv: float) -> tuple[float, float, float, float, float]:
    """``F = dFv |v|`` (coded ``(dFv, -, -)``) and its partials."""
    return dfv * abs(v), dfv * _sgn(v), abs(v), 0.0, 0.0


# ---------------------------------------------------------------------------------------------
# the table


@dataclass(frozen=True)
class LawParam:
    """One parameter of a law, as a model-node effect term carries it.

    Attributes:
        name: the term's field name (e.g. ``Fc``).
        unit: its unit on the model node's members (N m, rad/s, ...).
        lower, upper: admissible range; ``lo_open``: ``lower`` excluded.
        default: value when the term omits the field (``None``: required).
        doc: one line for the contract's description.
    """

    name: str
    unit: str
    lower: float
    upper: float
    lo_open: bool = False
    default: float | None = None
    doc: str = ""


TORQUE_MAX = 1e4
"""Largest admissible friction torque of a term [N m] (a plausibility bound, not physics)."""


@dataclass(frozen=True)
class Law:
    """One speed law.

    Attributes:
        name: the model-node term kind (``coulomb``, ...).
        code: the integer code of the identifier's compiled kernels (:func:`coded_value`).
        value: the law ``F(v, *params)`` (resisting force).
        params: the term's parameters, in the order :attr:`value` takes them after ``v``
            (a dry law's smoothing ``eps`` is added by the contract, :attr:`dry`).
        coded: the names of the coded ``(p0, p1, p2)`` (``eps`` for the smoothing, ``''``
            unused).
        dry: whether the law has a sign (a ``sign_eps`` smoothing speed ``eps``).
        doc: the formula, one line.
        example: typical coded ``(p0, p1, p2)`` (a dry law's ``eps`` > 0); the table's tests
            check every law's dispatch and partials there.
    """

    name: str
    code: int
    value: Callable[..., Any]
    params: tuple[LawParam, ...]
    coded: tuple[str, str, str]
    dry: bool
    doc: str
    example: tuple[float, float, float]

    def __call__(self, v: Any, fields: dict[str, float]) -> Any:
        """``F(v)`` with the parameters taken from a term's ``fields`` by name (a dry law's
        ``eps`` from ``fields['eps']``)."""
        args = [fields[p.name] if p.default is None else fields.get(p.name, p.default)
                for p in self.params]
        if self.dry:
            args.append(fields["eps"])
        return self.value(v, *args)


STRIBECK = 0
"""Code of :func:`stribeck` (coded ``(Fs, vs, eps)``, ``delta = 2``)."""
WINDAGE = 1
"""Code of :func:`windage` (coded ``(Cw, -, -)``)."""
ABS_VISCOUS = 2
"""Code of :func:`abs_viscous` (coded ``(dFv, -, -)``)."""
COULOMB = 3
"""Code of :func:`coulomb` without offset (coded ``(Fc, eps, -)``)."""
VISCOUS = 4
"""Code of :func:`viscous` (coded ``(b, -, -)``; not a candidate of the identifier: its
viscous drag is part of the linear structure)."""

LAWS: dict[str, Law] = {law.name: law for law in (
    Law("coulomb", COULOMB, coulomb, (
        LawParam("Fc", "N m", 0.0, TORQUE_MAX, doc="dry friction level, >= 0"),
        LawParam("offset", "N m", -TORQUE_MAX, TORQUE_MAX, default=0.0,
                 doc="constant torque against the positive direction")),
        ("Fc", "eps", ""), True, "Fc sign_eps(v) + offset", (0.9, 0.05, 0.0)),
    Law("stribeck", STRIBECK, stribeck, (
        LawParam("Fs", "N m", 0.0, TORQUE_MAX, doc="Stribeck excess, >= 0"),
        LawParam("vs", "rad/s", 0.0, 1e4, lo_open=True, doc="Stribeck speed, > 0")),
        ("Fs", "vs", "eps"), True, "Fs exp(-(v/vs)^2) sign_eps(v)", (0.4, 2.5, 0.05)),
    Law("windage", WINDAGE, windage, (
        LawParam("Cw", "N m s^2", 0.0, 1e3, doc="quadratic drag, >= 0"),),
        ("Cw", "", ""), False, "Cw |v| v", (0.01, 0.0, 0.0)),
    Law("viscous", VISCOUS, viscous, (
        LawParam("b", "N m s", 0.0, 1e3, doc="viscous drag, >= 0"),),
        ("b", "", ""), False, "b v", (0.003, 0.0, 0.0)),
    Law("abs_viscous", ABS_VISCOUS, abs_viscous, (
        LawParam("dFv", "N m s", -1e3, 1e3, doc="direction-dependent viscous friction"),),
        ("dFv", "", ""), False, "dFv |v|", (-0.02, 0.0, 0.0)),
)}
"""Every speed law by its model-node term kind."""

TERM_LAWS: tuple[str, ...] = ("coulomb", "stribeck", "windage", "viscous")
"""The laws the model node accepts as effect terms (the contract's force-term kinds);
``abs_viscous`` is the identifier's alone (the node has no direction-dependent term)."""


def law_of_code(code: int) -> Law:
    """The law with the compiled-kernel code ``code``.

    Raises:
        KeyError: no law has it.
    """
    for law in LAWS.values():
        if law.code == code:
            return law
    raise KeyError(f"no law has code {code} (codes: {sorted(w.code for w in LAWS.values())})")


# ---------------------------------------------------------------------------------------------
# dispatch on the code (compiled by the identifier: one branch per law)


def coded_value(code: int, p0: float, p1: float, p2: float, v: float) -> float:
    """The resisting force ``F(v)`` of the law with code ``code`` and coded parameters."""
    if code == STRIBECK:
        return stribeck(v, p0, p1, p2, 2.0)
    if code == WINDAGE:
        return windage(v, p0)
    if code == COULOMB:
        return coulomb(v, p0, 0.0, p1)
    if code == VISCOUS:
        return viscous(v, p0)
    return abs_viscous(v, p0)


def coded_partials(code: int, p0: float, p1: float, p2: float, v: float
                   ) -> tuple[float, float, float, float, float]:
    """``(F, dF/dv, dF/dp0, dF/dp1, dF/dp2)`` of the law with code ``code`` at ``v``."""
    if code == STRIBECK:
        return stribeck_partials(v, p0, p1, p2)
    if code == WINDAGE:
        return windage_partials(v, p0)
    if code == COULOMB:
        return coulomb_partials(v, p0, p1)
    if code == VISCOUS:
        return p0 * v, p0, v, 0.0, 0.0
    return abs_viscous_partials(v, p0)


def coded_eps(code: int, p1: float, p2: float) -> float:
    """The speed below which a coded law is stiff (its slope about ``p0`` over it): a smoothed
    sign's ``eps``; 0: the exact sign or a law held explicitly. The identifier holds a stiff
    law's force at the step's end (implicitly, within ``|F| <= |p0|``)."""
    if code == COULOMB:
        return p1
    if code == STRIBECK:
        return p2
    return 0.0


JITABLE: tuple[Callable[..., Any], ...] = (
    sign_eps, coulomb, stribeck, windage, viscous, abs_viscous, _sgn, coulomb_partials,
    stribeck_partials, windage_partials, abs_viscous_partials, coded_value, coded_partials,
    coded_eps)
"""The functions a compiled kernel may call (callees first), for ``register_jitable``."""
