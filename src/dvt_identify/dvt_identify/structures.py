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
from dvt_identify.effects.base import ParamSpec
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


_TERM = re.compile(r"\s*([+-])?\s*((?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)?\s*(\*)?\s*"
                   r"([A-Za-z_][A-Za-z0-9_]*)?\s*")


def _entry_terms(txt: str) -> list[tuple[float, str | None]] | None:
    """``txt`` as a sum of terms ``[sign][coef*]name`` or numbers (``"c + dm"``,
    ``"-k"``, ``"2*k - 0.5"``): ``(coefficient, name or None)`` each; ``None`` if not that."""
    out: list[tuple[float, str | None]] = []
    pos = 0
    while pos < len(txt):
        m = _TERM.match(txt, pos)
        if m is None or m.end() == pos:
            return None
        sign, num, star, name = m.groups()
        if (num is None and name is None) or (star and (num is None or name is None)):
            return None
        if out and sign is None:
            return None
        coef = float(num) if num is not None else 1.0
        out.append((-coef if sign == "-" else coef, name))
        pos = m.end()
    return out or None


class ParamMatrix:
    """A matrix whose entries are numbers or sums of ``[sign][coef*]name`` of parameters.

    Example: ``[[ "-Fv" ]]`` or ``[[A11, A12], [A21, A22]]`` or ``[[1.0, "0.5*k"]]`` or
    ``[["c + dm", "-c"], ["-c", "c + dl"]]``.
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
                terms = _entry_terms(txt)
                if terms is None or any(n is not None and n not in names for _, n in terms):
                    raise DescriptionError(f"{what}[{i}][{j}]: {txt!r} is not a number or a sum "
                                           f"of [-][coef*]parameter terms (parameters: "
                                           f"{', '.join(names)})")
                for coef, pname in terms:
                    if pname is None:
                        self.const[i, j] += coef
                    else:
                        self.terms.append((i, j, coef, list(names).index(pname)))

    def __call__(self, theta: Array) -> Array:
        out = self.const.copy()
        for i, j, c, k in self.terms:
            out[i, j] += c * theta[k]
        return out

    def derivative(self, p: int) -> Array:
        """``d M / d theta`` for ``p`` parameters, shape (p, nr, nc) (the matrix is linear in
        its parameters: the coefficients of each)."""
        out = np.zeros((p, *self.shape))
        for i, j, c, k in self.terms:
            out[k, i, j] += c
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

    def derivatives(self, theta: Array) -> tuple[Array, Array, Array]:
        """``dA``, ``dB``, ``dF`` by every parameter (the entries are linear in them)."""
        p = len(self.params)
        nx = len(self.state_names)
        dF = np.zeros((p, nx, nx)) if self._F is None else self._F.derivative(p)
        return self._A.derivative(p), self._B.derivative(p), dF


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

    def derivatives(self, theta: Array) -> tuple[Array, Array, Array]:
        """``dA``, ``dB``, ``dF`` by every parameter, shapes (p, nx, nx), (p, nx, nu),
        (p, nx, nx): ``d M^-1 = -M^-1 dM M^-1``; raises ``LinAlgError`` for a singular
        ``M``."""
        p = len(self.params)
        Minv = np.asarray(np.linalg.inv(self._M(theta)), dtype=float)
        dMinv = -Minv @ self._M.derivative(p) @ Minv
        D, Q = self._D(theta), self._Q(theta)
        return (-(dMinv @ D) - Minv @ self._D.derivative(p),
                dMinv @ Q + Minv @ self._Q.derivative(p), dMinv)


class SpringMechanicalStructure(LinearStructureBase):
    """``M q'' = -D q' - K q + Q u + tau`` with hidden states: members joined by springs.

    States ``x = [q; w]`` (nx = 2n): the members' angles (or positions), named
    ``<member>_angle``, then their speeds, named ``<member>``; ``A = [[0, I], [-M^-1 K,
    -M^-1 D]]``, ``B = [0; M^-1 Q]``, ``F`` maps a generalised force on a speed state to
    ``M^-1`` (zero rows and columns for the angles). ``K`` holds the springs: one between
    members ``a`` and ``b`` adds ``k`` to ``K_aa`` and ``K_bb`` and ``-k`` to ``K_ab``,
    ``K_ba``; one to ground adds ``k`` to ``K_aa`` only. A matrix entry may be a sum
    (``"c + dm"``).

    The outputs are any subset of the states, ``y = C x`` (``C`` (ny, nx) selects them):
    ``outputs`` maps each measured output name to a state name; a member that carries no
    sensor is a hidden state, and the fit estimates every initial state (angles included).

    Args:
        members: the member names (n).
        output_names: the measured outputs (the description's output names).
        input_names: nu input names.
        mass, damping, stiffness: (n, n) matrices; ``input_matrix`` (n, nu).
        outputs: output name -> state name (default: each output is the state of its name).

    Raises:
        DescriptionError: a wrong shape, an unknown state, a member named twice.
    """

    def __init__(self, members: Sequence[str], output_names: Sequence[str],
                 input_names: Sequence[str], mass: object, damping: object, stiffness: object,
                 input_matrix: object, parameters: dict[str, Any],
                 outputs: dict[str, str] | None = None, force_unit: str = "",
                 speed_unit: str = "", angle_unit: str = "", what: str = "structure") -> None:
        mem = [str(m) for m in members]
        if not mem or len(set(mem)) != len(mem):
            raise DescriptionError(f"{what}.members: expected distinct member names, got {mem}")
        states = [f"{m}_angle" for m in mem] + mem
        if len(set(states)) != len(states):
            raise DescriptionError(f"{what}.members: a member is named like another's angle "
                                   f"({states})")
        names, _, nu = self._init_names(states, input_names, parameters, what)
        n = len(mem)
        self.members = tuple(mem)
        self._M = ParamMatrix(mass, f"{what}.mass", names, (n, n))
        self._D = ParamMatrix(damping, f"{what}.damping", names, (n, n))
        self._K = ParamMatrix(stiffness, f"{what}.stiffness", names, (n, n))
        self._Q = ParamMatrix(input_matrix, f"{what}.input_matrix", names, (n, nu))
        outs = [str(o) for o in output_names]
        mapping = {o: o for o in outs} if outputs is None else {str(k): str(v)
                                                                for k, v in outputs.items()}
        missing = [o for o in outs if o not in mapping]
        extra = sorted(set(mapping) - set(outs))
        if missing or extra:
            raise DescriptionError(f"{what}.outputs: must map exactly the outputs {outs} to "
                                   f"states" + (f"; missing {missing}" if missing else "")
                                   + (f"; not outputs {extra}" if extra else ""))
        bad = sorted({v for v in mapping.values() if v not in states})
        if bad:
            raise DescriptionError(f"{what}.outputs: {bad} are not states (states: "
                                   f"{', '.join(states)})")
        self.output_names = tuple(outs)
        self.output_states = tuple(mapping[o] for o in outs)
        C = np.zeros((len(outs), 2 * n))
        for r, st in enumerate(self.output_states):
            C[r, states.index(st)] = 1.0
        self._C = C
        self.force_unit = force_unit
        self.speed_unit = speed_unit
        self.angle_unit = angle_unit

    def output_matrix(self) -> Array:
        """``C`` (ny, nx): the rows of the identity that select the measured states."""
        return self._C.copy()

    def mass_damping_stiffness(self, theta: Array) -> tuple[Array, Array, Array]:
        """``M``, ``D``, ``K`` (n, n) at ``theta``."""
        return self._M(theta), self._D(theta), self._K(theta)

    def matrices(self, theta: Array) -> tuple[Array, Array, Array]:
        """``A`` (2n, 2n), ``B`` (2n, nu), ``F`` (2n, 2n); raises ``LinAlgError`` for a
        singular ``M``."""
        n = len(self.members)
        Minv = np.asarray(np.linalg.inv(self._M(theta)), dtype=float)
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = -Minv @ self._K(theta)
        A[n:, n:] = -Minv @ self._D(theta)
        B = np.zeros((2 * n, len(self.input_names)))
        B[n:] = Minv @ self._Q(theta)
        F = np.zeros((2 * n, 2 * n))
        F[n:, n:] = Minv
        return A, B, F

    def derivatives(self, theta: Array) -> tuple[Array, Array, Array]:
        """``dA``, ``dB``, ``dF`` by every parameter (``d M^-1 = -M^-1 dM M^-1``); raises
        ``LinAlgError`` for a singular ``M``."""
        n = len(self.members)
        p = len(self.params)
        Minv = np.asarray(np.linalg.inv(self._M(theta)), dtype=float)
        dMinv = -Minv @ self._M.derivative(p) @ Minv
        K, D, Q = self._K(theta), self._D(theta), self._Q(theta)
        dA = np.zeros((p, 2 * n, 2 * n))
        dA[:, n:, :n] = -(dMinv @ K) - Minv @ self._K.derivative(p)
        dA[:, n:, n:] = -(dMinv @ D) - Minv @ self._D.derivative(p)
        dB = np.zeros((p, 2 * n, len(self.input_names)))
        dB[:, n:] = dMinv @ Q + Minv @ self._Q.derivative(p)
        dF = np.zeros((p, 2 * n, 2 * n))
        dF[:, n:, n:] = dMinv
        return dA, dB, dF

    def initial_state(self, y0: Array) -> Array:
        """A start for the initial state from the first measured outputs ``y0`` (ny,): measured
        states as measured, unmeasured speeds at the mean measured speed, unmeasured angles
        at the mean measured angle (0 when none is measured)."""
        n = len(self.members)
        x = np.zeros(2 * n)
        seen = np.zeros(2 * n, dtype=bool)
        for r, st in enumerate(self.output_states):
            k = self.state_names.index(st)
            x[k] = float(y0[r])
            seen[k] = True
        for part in (slice(0, n), slice(n, 2 * n)):
            s = seen[part]
            xs = x[part]
            xs[~s] = float(xs[s].mean()) if np.any(s) else 0.0
            x[part] = xs
        return x

    def initial_guess(self, segments: Sequence[Segment]) -> Array:
        """The parameters' initial values (the equation-error start of :class:`LinearStructureBase`
        needs every state measured)."""
        return np.array([p.initial for p in self.params], dtype=float)

    def modes(self, theta: Array) -> list[dict[str, float]]:
        """The oscillating modes of the linear part at ``theta``: undamped natural frequency
        [Hz] and damping ratio of each complex pair (upper half plane), slowest first."""
        A, _, _ = self.matrices(theta)
        lam = np.linalg.eigvals(A)
        out = []
        for v in sorted((v for v in lam if v.imag > 1e-9), key=lambda z: abs(z)):
            wn = abs(v)
            out.append({"frequency_hz": float(wn / (2 * math.pi)),
                        "damping_ratio": float(-v.real / wn)})
        return out

    def physical(self, theta: Array) -> dict[str, float]:
        """Parameters by name, then each mode's natural frequency and damping ratio."""
        out = super().physical(theta)
        try:
            for i, md in enumerate(self.modes(theta), start=1):
                out[f"mode{i}_frequency_hz"] = md["frequency_hz"]
                out[f"mode{i}_damping_ratio"] = md["damping_ratio"]
        except (np.linalg.LinAlgError, ValueError):
            pass
        return out


def matrix_derivatives(structure: ModelStructure, theta: Array, step: float = 1e-6
                       ) -> tuple[Array, Array, Array]:
    """``dA``, ``dB``, ``dF`` of ``structure.matrices`` by every parameter, shapes (p, nx, nx),
    (p, nx, nu), (p, nx, nx): the structure's own ``derivatives`` when it has them (exact),
    else central differences with relative step ``step``.

    Raises:
        np.linalg.LinAlgError, ValueError: the matrices cannot be formed at ``theta``.
    """
    fn = getattr(structure, "derivatives", None)
    if fn is not None:
        dA, dB, dF = fn(np.asarray(theta, float))
        return np.asarray(dA, float), np.asarray(dB, float), np.asarray(dF, float)
    th = np.asarray(theta, float)
    cols = []
    for j in range(th.size):
        h = step * max(abs(float(th[j])), 1e-8)
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        mp, mm = structure.matrices(tp), structure.matrices(tm)
        cols.append([(a - b) / (2 * h) for a, b in zip(mp, mm, strict=True)])
    A, B, F = structure.matrices(th)
    if not cols:
        return np.zeros((0, *A.shape)), np.zeros((0, *B.shape)), np.zeros((0, *F.shape))
    return (np.stack([c[0] for c in cols]), np.stack([c[1] for c in cols]),
            np.stack([c[2] for c in cols]))


def output_names(structure: ModelStructure) -> tuple[str, ...]:
    """The structure's measured outputs: its ``output_names`` when it has hidden states, else
    its states (C = I)."""
    return tuple(getattr(structure, "output_names", structure.state_names))


def output_matrix(structure: ModelStructure) -> Array | None:
    """``C`` (ny, nx) of a structure with hidden states, ``None`` for C = I."""
    fn = getattr(structure, "output_matrix", None)
    return None if fn is None else np.asarray(fn(), dtype=float)


def initial_state(structure: ModelStructure, y0: Array) -> Array:
    """A start for the initial state (nx,) from the first measured outputs ``y0`` (ny,)."""
    fn = getattr(structure, "initial_state", None)
    return np.asarray(y0, dtype=float).copy() if fn is None else np.asarray(fn(y0), float)
