"""Drawing a hidden-effect preset's magnitudes, reductions and orders from a seed (pure).

A preset (``config/*.yaml``) may give a value as a distribution instead of a number: the
simulated plant then draws it from the run's seed, so the plant's truth is not a value anyone
could have copied into the identifier's priors, and tests compare identified values with the
drawn truth (written into ``truth.yaml``). A distribution is a mapping with exactly one of

- ``uniform: [lo, hi]``: uniform on ``[lo, hi]``;
- ``log_uniform: [lo, hi]`` (``0 < lo``): ``exp`` of a uniform on ``[log lo, log hi]`` (a
  magnitude whose order is uncertain);
- ``choice: [v1, v2, ...]``: one of the values, equally likely (a reduction, a stage, an
  order, a delay in whole samples);

and ``fixed: v``, the value of the *fixed draw* (the preset's single nominal plant, e.g.
``dvt-plant --hidden-fixed``), which must lie in ``[lo, hi]`` or among the choices. Example::

    coulomb:
      sun: {log_uniform: [0.03, 0.08], fixed: 0.05}
    mesh_ripple:
      stage: {choice: [1, 2, 3], fixed: 1}

:func:`resolve` replaces every distribution by its draw (``draw`` = a seed ``>= 0``) or by its
fixed value (``draw`` = ``None``). Each value is drawn from its own random stream, keyed by the
seed and the value's key path (``coulomb.sun``): adding an effect to a preset does not change
the other effects' draws, and the draw does not share a stream with the plant's sensor noise
(which uses the same seed). Drawn numbers are rounded to 4 significant digits (the plant runs
exactly the value ``truth.yaml`` states). :func:`draw_record` is what ``truth.yaml`` stores
under ``hidden_draw``: the seed and each distribution by key path.
"""

from __future__ import annotations

import math
import secrets
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from dvt_driver.errors import HiddenEffectsError

__all__ = ["DISTRIBUTIONS", "DRAW_STREAM", "draw_record", "is_distribution", "random_draw",
           "resolve"]

DISTRIBUTIONS: tuple[str, ...] = ("uniform", "log_uniform", "choice")
"""Kinds of distribution a preset value may be (module docstring)."""

DRAW_STREAM = 0x68696464
"""First word of every draw's seed sequence (``[DRAW_STREAM, seed, crc32(path)]``): keeps the
draws apart from the plant's noise generator, which is seeded with the bare seed."""

SIGNIFICANT_DIGITS = 4
"""Drawn numbers are rounded to this many significant digits."""


def is_distribution(value: Any) -> bool:
    """True for a mapping that names a distribution (or only its ``fixed`` value)."""
    return isinstance(value, Mapping) and any(k in value for k in (*DISTRIBUTIONS, "fixed"))


def random_draw() -> int:
    """A fresh draw seed (for a plant run without ``--seed``), in ``[0, 2^31)``."""
    return secrets.randbelow(2 ** 31)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise HiddenEffectsError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _check(spec: Mapping[str, Any], where: str) -> tuple[str, list[Any], Any]:
    """``(kind, arguments, fixed)`` of a distribution mapping, validated."""
    kinds = [k for k in DISTRIBUTIONS if k in spec]
    extra = [k for k in spec if k not in (*DISTRIBUTIONS, "fixed")]
    if extra:
        raise HiddenEffectsError(f"{where}.{extra[0]}: unknown key in a distribution (expected "
                                 f"one of {list(DISTRIBUTIONS)} and 'fixed'), value "
                                 f"{spec[extra[0]]!r}")
    if len(kinds) != 1:
        raise HiddenEffectsError(f"{where}: a distribution needs exactly one of "
                                 f"{list(DISTRIBUTIONS)}, got {dict(spec)!r}")
    if "fixed" not in spec:
        raise HiddenEffectsError(f"{where}.fixed: missing (the value of the fixed draw, "
                                 f"e.g. dvt-plant --hidden-fixed), distribution {dict(spec)!r}")
    kind = kinds[0]
    args = spec[kind]
    if not isinstance(args, list) or not args:
        raise HiddenEffectsError(f"{where}.{kind}: expected a non-empty list, got {args!r}")
    fixed = spec["fixed"]
    if kind == "choice":
        for i, v in enumerate(args):
            _number(v, f"{where}.choice[{i}]")
        _number(fixed, f"{where}.fixed")
        if fixed not in args:
            raise HiddenEffectsError(f"{where}.fixed: {fixed!r} is not one of the choices "
                                     f"{args}")
        return kind, list(args), fixed
    if len(args) != 2:
        raise HiddenEffectsError(f"{where}.{kind}: expected [lo, hi], got {args!r}")
    lo, hi = (_number(v, f"{where}.{kind}") for v in args)
    if not lo < hi:
        raise HiddenEffectsError(f"{where}.{kind}: expected lo < hi, got {args!r}")
    if kind == "log_uniform" and not lo > 0:
        raise HiddenEffectsError(f"{where}.log_uniform: expected 0 < lo, got {args!r}")
    f = _number(fixed, f"{where}.fixed")
    if not lo <= f <= hi:
        raise HiddenEffectsError(f"{where}.fixed: {fixed!r} is outside {kind} {args}")
    return kind, [lo, hi], fixed


def _round(x: float) -> float:
    return float(f"{x:.{SIGNIFICANT_DIGITS}g}")


def _draw_one(kind: str, args: list[Any], path: str, draw: int) -> Any:
    rng = np.random.default_rng([DRAW_STREAM, draw, zlib.crc32(path.encode())])
    if kind == "choice":
        return args[int(rng.integers(len(args)))]
    lo, hi = float(args[0]), float(args[1])
    if kind == "uniform":
        return _round(lo + (hi - lo) * float(rng.random()))
    return _round(math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * float(rng.random())))


def resolve(data: Any, draw: int | None, source: str = "<mapping>"
            ) -> tuple[Any, dict[str, dict[str, Any]]]:
    """Replace every distribution in ``data`` (a decoded preset) by a value.

    Args:
        data: the decoded YAML (mappings, lists, numbers, text).
        draw: the seed of the draw (an integer ``>= 0``), or ``None`` for the fixed draw.
        source: the file or preset name, for messages.

    Returns:
        ``(resolved, distributions)``: ``data`` with numbers in place of distributions, and
        each distribution by its key path (``coulomb.sun``; list items ``changes[0]``), as
        given.

    Raises:
        HiddenEffectsError: a malformed distribution (naming the source, the key path and the
            value) or a negative seed.
    """
    if draw is not None and (isinstance(draw, bool) or not isinstance(draw, int) or draw < 0):
        raise HiddenEffectsError(f"{source}: the draw seed must be an integer >= 0, got "
                                 f"{draw!r}")
    found: dict[str, dict[str, Any]] = {}

    def walk(node: Any, path: str) -> Any:
        if is_distribution(node):
            kind, args, fixed = _check(node, f"{source}: {path}")
            found[path] = {kind: list(args), "fixed": fixed}
            return fixed if draw is None else _draw_one(kind, args, path, draw)
        if isinstance(node, Mapping):
            return {k: walk(v, f"{path}.{k}" if path else str(k)) for k, v in node.items()}
        if isinstance(node, list):
            return [walk(v, f"{path}[{i}]") for i, v in enumerate(node)]
        return node

    return walk(data, ""), found


def draw_record(draw: int | None, distributions: Mapping[str, Mapping[str, Any]]
                ) -> dict[str, Any] | None:
    """What ``truth.yaml`` stores under ``hidden_draw`` (``None`` without a distribution):
    ``seed`` (``None``: the fixed draw), ``fixed`` (bool) and ``distributions`` by key path."""
    if not distributions:
        return None
    return {"seed": draw, "fixed": draw is None,
            "distributions": {p: dict(d) for p, d in distributions.items()}}
