"""Linear model structures of the output-error models and their equation-error start.

Model (C = I, K = 0, states = outputs)::

    x' = A(theta) x + B(theta) u_eff + F(theta) sum_e c_e tau_e,     y = h(x)

``A`` (nx, nx) [1/s], ``B`` (nx, nu) and ``F`` (nx, nx, generalised force -> state derivative)
come from a :class:`ModelStructure`; the effect terms from :mod:`dvt_identify.effects`. This
module holds the structures (free state space, mechanical ``M x' = -D x + Q u + tau``), the
parametrised matrices they are written with (:class:`ParamMatrix`) and the equation-error
estimate of ``(A, B)`` that gives a fit its first start (:func:`equation_error_ab`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from scipy import signal
from scipy.optimize import least_squares

from dvt_identify.data import Segment
from dvt_identify.effects import ParamSpec
from dvt_identify.errors import DescriptionError

Array = NDArray[np.float64]
PENALTY = 1e6
"""Residual of an unusable parameter vector (singular or non-finite matrices, diverged
simulation): large, finite, so that the bounded least squares steers away from it."""

# ---------------------------------------------------------------------------------------------
# Structures


@runtime_checkable
class ModelStructure(Protocol):
    """The linear part of a model, parametrised by ``theta`` (shape (p,)).

    Attributes:
        state_names: names of the states = outputs (C = I), length nx.
        input_names: names of the inputs, length nu.
        params: one :class:`~dvt_identify.effects.ParamSpec` per entry of ``theta``.
        force_unit: unit of a generalised force in effect reports (``N``, ``N m``, ...).
        speed_unit: unit of the states (``m/s``, ``rad/s``).
    """

    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    params: tuple[ParamSpec, ...]
    force_unit: str
    speed_unit: str

    def matrices(self, theta: Array) -> tuple[Array, Array, Array]:
        """``A`` (nx, nx) [1/s], ``B`` (nx, nu), ``F`` (nx, nx) for ``theta``."""
        ...

    def initial_guess(self, segments: Sequence[Segment]) -> Array:
        """A start value of ``theta``, shape (p,), from data and/or physics."""
        ...

    def physical(self, theta: Array) -> dict[str, float]:
        """Physical parameters to report (name -> value) for ``theta``."""
        ...


_ENTRY = re.compile(r"^\s*([+-]?)\s*((?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)?\s*\*?\s*"
                    r"([A-Za-z_][A-Za-z0-9_]*)\s*$")


class ParamMatrix:
    """A matrix whose entries are numbers or ``[sign][coef*]name`` of a parameter.

    Example: ``[[ "-Fv" ]]`` or ``[[A11, A12], [A21, A22]]`` or ``[[1.0, "0.5*k"]]``.
    """

    def __init__(self, spec: object, what: str, names: Sequence[str],
                 shape: tuple[int, int] | None = None) -> None:
        rows = spec if isinstance(spec, list) else None
        if rows is None or not rows or not all(isinstance(r, list) for r in rows):
            raise DescriptionError(f"{what}: expected a list of rows (matrix), got {spec!r}")
        nr, nc = len(rows), len(rows[0])
        if any(len(r) != nc for r in rows):
            raise DescriptionError(f"{what}: rows of different length: {spec!r}")
        if shape is not None and (nr, nc) != shape:
            raise DescriptionError(f"{what}: expected shape {shape}, got {(nr, nc)}")
        self.shape = (nr, nc)
        self.const = np.zeros(self.shape)
        self.terms: list[tuple[int, int, float, int]] = []
        for i, row in enumerate(rows):
            for j, e in enumerate(row):
                if isinstance(e, bool):
                    raise DescriptionError(f"{what}[{i}][{j}]: not a number or name: {e!r}")
                if isinstance(e, int | float):
                    self.const[i, j] = float(e)
                    continue
                txt = str(e)
                try:
                    self.const[i, j] = float(txt)
                    continue
                except ValueError:
                    pass
                m = _ENTRY.match(txt)
                if m is None or m.group(3) not in names:
                    raise DescriptionError(f"{what}[{i}][{j}]: {txt!r} is not a number or "
                                           f"[-][coef*]parameter (parameters: "
                                           f"{', '.join(names)})")
                coef = float(m.group(2)) if m.group(2) else 1.0
                if m.group(1) == "-":
                    coef = -coef
                self.terms.append((i, j, coef, list(names).index(m.group(3))))

    def __call__(self, theta: Array) -> Array:
        out = self.const.copy()
        for i, j, c, k in self.terms:
            out[i, j] += c * theta[k]
        return out


def equation_error_ab(segments: Sequence[Segment], cutoff_fraction: float = 0.04
                      ) -> tuple[Array, Array]:
    """Equation-error LS estimate of ``x' = A x + B u`` (continuous time).

    Inputs and outputs pass the same zero-phase Butterworth low-pass (order 4, cutoff
    ``cutoff_fraction`` x sample rate), which leaves a linear relation unchanged and only removes
    noise; ``x'`` is a central difference; 5 % is trimmed at each end.

    Returns:
        ``A`` shape (nx, nx), ``B`` shape (nx, nu).
    """
    rows_x, rows_d = [], []
    for seg in segments:
        fs = 1.0 / seg.dt
        cut = min(cutoff_fraction * fs, 0.45 * fs)
        sos = signal.butter(4, cut, fs=fs, output="sos")
        pad = min(seg.n - 2, 3 * 27)
        yf = signal.sosfiltfilt(sos, seg.y, axis=0, padlen=pad)
        uf = signal.sosfiltfilt(sos, seg.u, axis=0, padlen=pad)
        dy = np.gradient(yf, seg.dt, axis=0)
        k = max(1, seg.n // 20)
        rows_x.append(np.hstack([yf, uf])[k:-k])
        rows_d.append(dy[k:-k])
    X = np.vstack(rows_x)
    D = np.vstack(rows_d)
    scale = np.std(X, axis=0)
    scale[scale == 0] = 1.0
    theta, *_ = np.linalg.lstsq(X / scale, D, rcond=None)
    theta = theta / scale[:, None]
    nx = segments[0].y.shape[1]
    return np.asarray(theta[:nx].T), np.asarray(theta[nx:].T)


class LinearStructureBase:
    """Shared behaviour of structures: initial guess by fitting ``theta`` to equation-error
    ``(A, B)`` (starting from the specs' initial values), physical = parameters by name.

    Subclasses set ``state_names``, ``input_names``, ``params``, ``force_unit``, ``speed_unit``
    and implement :meth:`matrices`.
    """

    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    params: tuple[ParamSpec, ...] = ()
    force_unit: str = ""
    speed_unit: str = ""

    def _init_names(self, state_names: Sequence[str], input_names: Sequence[str],
                    parameters: dict[str, Any], what: str) -> tuple[list[str], int, int]:
        """Set names and parameter specs; return (parameter names, nx, nu)."""
        self.state_names = tuple(state_names)
        self.input_names = tuple(input_names)
        self.params = _param_specs(parameters, what)
        return [p.name for p in self.params], len(self.state_names), len(self.input_names)

    def matrices(self, theta: Array) -> tuple[Array, Array, Array]:  # pragma: no cover
        raise NotImplementedError

    def initial_guess(self, segments: Sequence[Segment]) -> Array:
        """Equation-error ``(A, B)`` mapped to ``theta`` by bounded least squares on the matrix
        entries (each matrix normalised by its norm); the specs' initial values if that fails."""
        theta0 = np.array([p.initial for p in self.params], dtype=float)
        if not self.params:
            return theta0
        try:
            A_ls, B_ls = equation_error_ab(segments)
        except (ValueError, np.linalg.LinAlgError):
            return theta0
        na = float(np.linalg.norm(A_ls)) or 1.0
        nb = float(np.linalg.norm(B_ls)) or 1.0

        def res(th: Array) -> Array:
            try:
                A, B, _ = self.matrices(th)
            except (np.linalg.LinAlgError, ValueError):
                return np.full(A_ls.size + B_ls.size, PENALTY)
            r = np.concatenate([((A - A_ls) / na).ravel(), ((B - B_ls) / nb).ravel()])
            return np.asarray(np.nan_to_num(r, nan=PENALTY, posinf=PENALTY,
                                            neginf=-PENALTY))
        lo = np.array([p.lower for p in self.params])
        hi = np.array([p.upper for p in self.params])
        try:
            r = least_squares(res, theta0, bounds=(lo, hi), x_scale="jac", max_nfev=200)
        except ValueError:
            return theta0
        return np.asarray(r.x) if np.all(np.isfinite(r.x)) else theta0

    def physical(self, theta: Array) -> dict[str, float]:
        """Parameters by name."""
        return {p.name: float(v) for p, v in zip(self.params, theta, strict=True)}


def _param_specs(params: dict[str, Any], what: str) -> tuple[ParamSpec, ...]:
    out = []
    for name, spec in params.items():
        if not isinstance(spec, dict):
            spec = {"initial": spec}
        try:
            out.append(ParamSpec(name=str(name), initial=float(spec.get("initial", 0.0)),
                                 lower=float(spec.get("lower", -math.inf)),
                                 upper=float(spec.get("upper", math.inf)),
                                 unit=str(spec.get("unit", ""))))
        except (TypeError, ValueError) as exc:
            raise DescriptionError(f"{what}.parameters.{name}: {exc}") from exc
    return tuple(out)


class StateSpaceStructure(LinearStructureBase):
    """``x' = A x + B u + F tau`` with entries of ``A``, ``B`` (and optional ``F``, default I)
    given as numbers or parameter names (free 2x2 ``A``, ``B`` of the thesis: every entry named).
    """

    def __init__(self, state_names: Sequence[str], input_names: Sequence[str], A: object,
                 B: object, parameters: dict[str, Any], force_map: object | None = None,
                 force_unit: str = "", speed_unit: str = "", what: str = "structure") -> None:
        names, nx, nu = self._init_names(state_names, input_names, parameters, what)
        self._A = ParamMatrix(A, f"{what}.A", names, (nx, nx))
        self._B = ParamMatrix(B, f"{what}.B", names, (nx, nu))
        self._F = None if force_map is None else ParamMatrix(force_map, f"{what}.force_map",
                                                             names, (nx, nx))
        self.force_unit = force_unit or f"({speed_unit})/s" if speed_unit else force_unit
        self.speed_unit = speed_unit

    def matrices(self, theta: Array) -> tuple[Array, Array, Array]:
        """``A``, ``B`` from the entries; ``F`` = identity unless given."""
        nx = len(self.state_names)
        F = np.eye(nx) if self._F is None else self._F(theta)
        return self._A(theta), self._B(theta), F


class MechanicalStructure(LinearStructureBase):
    """``M x' = -D x + Q u + tau``: ``A = -M^-1 D``, ``B = M^-1 Q``, ``F = M^-1``.

    ``M`` (mass/inertia), ``D`` (viscous damping) and ``Q`` (input to generalised force) have
    entries given as numbers or parameter names; e.g. the EMPS drive ``M v' = F - Fv v`` is
    ``mass [[M]]``, ``damping [[Fv]]``, ``input_matrix [[1.0]]`` with ``F`` in N.
    """

    def __init__(self, state_names: Sequence[str], input_names: Sequence[str], mass: object,
                 damping: object, input_matrix: object, parameters: dict[str, Any],
                 force_unit: str = "", speed_unit: str = "", what: str = "structure") -> None:
        names, nx, nu = self._init_names(state_names, input_names, parameters, what)
        self._M = ParamMatrix(mass, f"{what}.mass", names, (nx, nx))
        self._D = ParamMatrix(damping, f"{what}.damping", names, (nx, nx))
        self._Q = ParamMatrix(input_matrix, f"{what}.input_matrix", names, (nx, nu))
        self.force_unit = force_unit
        self.speed_unit = speed_unit

    def matrices(self, theta: Array) -> tuple[Array, Array, Array]:
        """``(-M^-1 D, M^-1 Q, M^-1)``; raises ``LinAlgError`` for a singular ``M``."""
        Minv = np.asarray(np.linalg.inv(self._M(theta)), dtype=float)
        return -Minv @ self._D(theta), Minv @ self._Q(theta), Minv
