"""Continuous-time output-error models: structures, exact ZOH simulation and the OE fit.

Model (C = I, K = 0, states = outputs)::

    x' = A(theta) x + B(theta) u_eff + F(theta) sum_e c_e tau_e,     y = h(x)

``A`` (nx, nx), ``B`` (nx, nu) and ``F`` (nx, nx, generalised force -> state derivative) come from
a :class:`ModelStructure`; the effect terms (``c_e``, ``tau_e``, input transform ``u -> u_eff``,
output transform ``h``) from :mod:`dvt_identify.effects`.

Simulation is an exact zero-order-hold discretisation of the linear part (``scipy.linalg.expm``
of ``[[A, I], [0, 0]] dt``) with every effect term evaluated at the start of a step and held over
it. Models whose effects are all exogenous (no state-dependent force) are simulated in modal form
with ``scipy.signal.lfilter`` (vectorised); otherwise a step loop (compiled with numba,
:mod:`dvt_identify.simloop`) applies dry friction with a stick rule: a member speed that would
cross zero within a step is set to zero, and it stays zero while the force needed to hold it is
within the friction capacity.

:class:`OEFit` minimises the simulation error with ``scipy.optimize.least_squares`` (bounded
``trf``), outputs weighted by ``1/std(y_j)``, each segment with its own estimated initial state,
from several starts (equation-error/physics guess plus random perturbations).
"""

from __future__ import annotations

import math
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from scipy import signal
from scipy.linalg import expm
from scipy.optimize import least_squares

from dvt_identify.data import Segment, decimate
from dvt_identify.effects import Effect, ParamSpec, SegmentView, fixed_names
from dvt_identify.errors import DescriptionError, FitError
from dvt_identify.metrics import parameter_std
from dvt_identify.simloop import loop_members, loop_scalar, smooth_value

Array = NDArray[np.float64]
Progress = Callable[[str], None]
_BIG = 1e6


def stderr_progress(msg: str) -> None:
    """Print a progress line to stderr."""
    print(f"[dvt-identify] {msg}", file=sys.stderr, flush=True)


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
                return np.full(A_ls.size + B_ls.size, _BIG)
            r = np.concatenate([((A - A_ls) / na).ravel(), ((B - B_ls) / nb).ravel()])
            return np.asarray(np.nan_to_num(r, nan=_BIG, posinf=_BIG, neginf=-_BIG))
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


# ---------------------------------------------------------------------------------------------
# Simulation


_ZOH_CACHE: dict[tuple[bytes, float], tuple[Array, Array]] = {}


def zoh(A: Array, dt: float) -> tuple[Array, Array]:
    """Exact ZOH: ``Ad = e^{A dt}``, ``Gd = int_0^dt e^{A s} ds`` (both (nx, nx)); cached."""
    key = (np.ascontiguousarray(A, dtype=float).tobytes(), float(dt))
    hit = _ZOH_CACHE.get(key)
    if hit is not None:
        return hit
    out = _zoh(A, dt)
    if len(_ZOH_CACHE) > 256:
        _ZOH_CACHE.clear()
    _ZOH_CACHE[key] = out
    return out


def _zoh(A: Array, dt: float) -> tuple[Array, Array]:
    nx = A.shape[0]
    M = np.zeros((2 * nx, 2 * nx))
    M[:nx, :nx] = A * dt
    M[:nx, nx:] = np.eye(nx) * dt
    E = expm(M)
    return np.asarray(E[:nx, :nx]), np.asarray(E[:nx, nx:])


def simulate_linear(Ad: Array, d: Array, x0: Array) -> Array:
    """``x[k+1] = Ad x[k] + d[k]``, ``x[0] = x0``; returns x, shape (N, nx).

    Vectorised in modal coordinates with ``lfilter`` (one first-order recursion per eigenvalue);
    a plain loop when ``Ad`` is close to defective.
    """
    n, nx = d.shape
    lam, V = np.linalg.eig(Ad)
    if np.linalg.cond(V) > 1e8:
        x = np.empty((n, nx))
        x[0] = x0
        for k in range(n - 1):
            x[k + 1] = Ad @ x[k] + d[k]
        return x
    real = bool(np.all(np.abs(lam.imag) < 1e-300)) and bool(np.all(np.abs(V.imag) < 1e-300))
    if real:
        lam, V = lam.real, V.real
    Vi = np.linalg.inv(V)
    q = d @ Vi.T
    z0 = Vi @ x0
    kk = np.arange(n)
    z = np.empty((n, nx), dtype=q.dtype)
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(nx):
            z[:, i] = signal.lfilter([0.0, 1.0], [1.0, -lam[i]], q[:, i]) + lam[i] ** kk * z0[i]
        x = (z @ V.T).real
    return np.asarray(x, dtype=float)


SmoothLaw = tuple[int, float, float]
"""A coded smooth member force ``(kind, p0, p1)`` (:mod:`dvt_identify.simloop`)."""


def simulate_loop(A: Array, Ad: Array, Gd: Array, F: Array, w: Array, d: Array, x0: Array,
                  smooth: Sequence[tuple[Array, SmoothLaw]],
                  dry: Sequence[tuple[Array, Array | float, float]], reference: bool = False
                  ) -> Array:
    """Step loop with state-dependent member forces held over each step (compiled kernels of
    :mod:`dvt_identify.simloop`).

    Args:
        A, Ad, Gd, F: continuous ``A``, its ZOH ``Ad``, ``Gd`` and the force map ``F``.
        w: generalised input ``B u_eff + F f_exo`` per sample [state unit/s], shape (N, nx).
        d: ``w @ Gd.T``, shape (N, nx).
        x0: initial state, shape (nx,).
        smooth: (member c, law) pairs: force ``g(c.x)`` with the law coded ``(kind, p0, p1)``.
        dry: (member c, capacity (number or shape (N,)), breakaway) triples; capacities of
            the same member add up.
        reference: run the kernels' Python source in the interpreter instead of the compiled
            code (slow; for checking the compilation).

    Returns:
        States, shape (N, nx).
    """
    n, nx = d.shape
    groups: dict[tuple[float, ...], list[Any]] = {}
    for c, cap, brk in dry:
        key = tuple(float(v) for v in c)
        capv: Array | float = np.asarray(cap, float) if np.ndim(cap) else float(cap)
        if key in groups:
            grp = groups[key]
            grp[0] = grp[0] + capv
            grp[1] += brk
        else:
            groups[key] = [capv, brk]
    members = loop_members.py_func if reference else loop_members
    scalar = loop_scalar.py_func if reference else loop_scalar
    ns = len(smooth)
    sc = np.array([np.asarray(c, np.float64) for c, _ in smooth],
                  dtype=np.float64).reshape(ns, nx)
    skind = np.array([int(law[0]) for _, law in smooth], dtype=np.int64)
    spar = np.array([[float(law[1]), float(law[2])] for _, law in smooth],
                    dtype=np.float64).reshape(ns, 2)
    GdF = Gd @ F
    sfc = np.array([F @ c for c in sc], dtype=np.float64).reshape(ns, nx)
    sgd = np.array([GdF @ c for c in sc], dtype=np.float64).reshape(ns, nx)
    w = np.ascontiguousarray(w, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    if nx == 1:
        # one state: every dry member lumped in generalised coordinates
        cap = np.zeros(n)
        brk = 0.0
        gdf_unit = fmap = 1.0
        for key, (capv, b) in groups.items():
            c0 = key[0]
            cap = cap + abs(c0) * np.broadcast_to(np.asarray(capv, float), (n,))
            brk += abs(c0) * float(b)
            fc = float(F[0, 0]) * c0
            gdf_unit = float(Gd[0, 0]) * fc / c0
            fmap = fc / c0
        extra0 = sum(smooth_value(int(k), float(p[0]), float(p[1]), 0.0) * float(c[0])
                     for k, p, c in zip(skind, spar, sc, strict=True))
        x = scalar(float(A[0, 0]), float(Ad[0, 0]), w[:, 0].copy(), d[:, 0].copy(),
                   float(x0[0]), sc[:, 0].copy(), skind, spar, sgd[:, 0].copy(), bool(groups),
                   np.ascontiguousarray(cap), float(brk), gdf_unit, fmap, float(extra0))
        return np.asarray(x, dtype=float)[:, None]
    nd = len(groups)
    dc = np.array([np.array(key) for key in groups], dtype=np.float64).reshape(nd, nx)
    dcap = np.empty((nd, n))
    dbrk = np.empty(nd)
    for g, (capv, b) in enumerate(groups.values()):
        dcap[g] = np.broadcast_to(np.asarray(capv, float), (n,))
        dbrk[g] = float(b)
    dfcv = np.array([F @ c for c in dc], dtype=np.float64).reshape(nd, nx)
    dgdf = np.array([Gd @ f for f in dfcv], dtype=np.float64).reshape(nd, nx)
    dcfc = np.array([float(c @ f) for c, f in zip(dc, dfcv, strict=True)], dtype=np.float64)
    return np.asarray(members(np.ascontiguousarray(A, np.float64),
                              np.ascontiguousarray(Ad, np.float64), w, d,
                              np.array(x0, np.float64), sc, skind, spar, sgd, sfc, dc, dcap,
                              dbrk, dgdf, dfcv, dcfc), dtype=np.float64)


class OEModel:
    """A structure plus effects: the full parameter vector is ``[theta_structure, p_e1, ...]``.

    Args:
        structure: the linear part (:class:`ModelStructure`).
        effects: effect terms (instances from :func:`dvt_identify.effects.make_effect`).

    Raises:
        DescriptionError: duplicate parameter names.
    """

    def __init__(self, structure: ModelStructure, effects: Sequence[Effect] = ()) -> None:
        self.structure = structure
        self.effects = tuple(effects)
        specs: list[ParamSpec] = list(structure.params)
        self._slices: list[slice] = []
        fixed: set[str] = set()
        for e in self.effects:
            self._slices.append(slice(len(specs), len(specs) + len(e.params)))
            specs.extend(e.params)
            fixed.update(fixed_names(e))
        names = [s.name for s in specs]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise DescriptionError(f"duplicate parameter names: {', '.join(dup)}")
        self.specs = tuple(specs)
        self.names = tuple(names)
        self.free = np.array([n not in fixed for n in names], dtype=bool)
        self.n_struct = len(structure.params)
        self.nonlinear = any(e.state_dependent for e in self.effects)

    @property
    def nx(self) -> int:
        """Number of states = outputs."""
        return len(self.structure.state_names)

    def initial(self) -> Array:
        """Initial values of every parameter, shape (p,)."""
        return np.array([s.initial for s in self.specs], dtype=float)

    def effect_params(self, theta: Array) -> list[Array]:
        """Each effect's slice of ``theta``."""
        return [theta[s] for s in self._slices]

    def simulate(self, theta: Array, seg: Segment, x0: Array) -> Array:
        """Simulated outputs, shape (N, ny), for parameters ``theta`` and initial state ``x0``.

        Raises:
            FitError: ``theta`` has the wrong length.
        """
        if theta.shape != (len(self.specs),):
            raise FitError(f"theta: expected shape ({len(self.specs)},), got {theta.shape}")
        A, B, F = self.structure.matrices(theta[: self.n_struct])
        ps = self.effect_params(theta)
        u = seg.u
        for e, p in zip(self.effects, ps, strict=True):
            ut = e.input_transform(p, u, seg.dt)
            if ut is not None:
                u = ut
        # effects see the transformed inputs (a brake's capacity follows its engagement lag)
        view = SegmentView(seg.dt, u, seg.y)
        w = u @ B.T
        smooth: list[tuple[Array, SmoothLaw]] = []
        dry: list[tuple[Array, Array | float, float]] = []
        brk: dict[tuple[float, ...], float] = {}
        for e, p in zip(self.effects, ps, strict=True):
            f = e.exogenous_force(p, view)
            if f is not None and e.member is not None:
                w = w + np.outer(f, F @ e.member)
            if e.state_dependent and e.member is not None:
                law = e.smooth_law(p)
                if law is not None:
                    smooth.append((e.member, law))
                b = e.breakaway(p)
                if b:
                    key = tuple(float(v) for v in e.member)
                    brk[key] = brk.get(key, 0.0) + b
                cap = e.dry_capacity(p, view)
                if cap is not None:
                    dry.append((e.member, cap, 0.0))
        if brk and dry:
            used: set[tuple[float, ...]] = set()
            with_brk = []
            for c, cap, _ in dry:
                key = tuple(float(v) for v in c)
                with_brk.append((c, cap, 0.0 if key in used else brk.get(key, 0.0)))
                used.add(key)
            dry = with_brk
        Ad, Gd = zoh(A, seg.dt)
        d = w @ Gd.T
        if smooth or dry:
            x = simulate_loop(A, Ad, Gd, F, w, d, np.asarray(x0, float), smooth, dry)
        else:
            x = simulate_linear(Ad, d, np.asarray(x0, float))
        y = x
        for e, p in zip(self.effects, ps, strict=True):
            yt = e.output_transform(p, y, seg.dt)
            if yt is not None:
                y = yt
        return y

    def parameters(self, theta: Array) -> dict[str, float]:
        """Physical parameters of the structure, every effect parameter and derived figures."""
        out = dict(self.structure.physical(theta[: self.n_struct]))
        allv = {n: float(v) for n, v in zip(self.names, theta, strict=True)}
        for e, p in zip(self.effects, self.effect_params(theta), strict=True):
            out.update({s.name: float(v) for s, v in zip(e.params, p, strict=True)})
        for e in self.effects:
            out.update(e.derived({**allv, **out}))
        return out


def _x0_guess(seg: Segment) -> Array:
    return np.asarray(seg.y[: min(3, seg.n)].mean(axis=0), dtype=float)


def _clean(r: Array) -> Array:
    return np.asarray(np.clip(np.nan_to_num(r, nan=_BIG, posinf=_BIG, neginf=-_BIG), -_BIG, _BIG))


@dataclass(frozen=True)
class StartResult:
    """One start of a multi-start fit: start point, end point, cost at the end point on the full
    data, evaluations, scipy status, how it ran (``note``) and, for a screened start, whether it
    reached the first start's minimum (screening cost within 0.1 % of the reference)."""

    start: tuple[float, ...]
    theta: tuple[float, ...]
    cost: float
    nfev: int
    status: int
    note: str = ""
    same_minimum: bool | None = None


class OEFit:
    """Output-error fit of an :class:`OEModel` to segments (each with its own initial state).

    Args:
        model: structure + effects.
        starts: number of starts: the guess (run to convergence), then ``extra_starts``, then
            random perturbations of the structure's parameters by factors in [1/3, 3]; only
            starts with a stable linear part and a non-zero B are used. Starts after the first
            get ``screen_nfev`` evaluations on decimated data and are run to convergence on the
            full data only if they are then already better than the first.
        seed: random seed of the perturbations.
        theta0: start value of all parameters (default: structure guess + effects' initial).
        extra_starts: further full start vectors tried before the random ones.
        weights: output scale (ny,); residuals are divided by it (default std(y) pooled).
        max_nfev: cap on function evaluations per start (``None``: scipy's default).
        progress: called with progress lines.
        screen_nfev: evaluation budget of the screened starts.
        screen_samples: screened starts run on the data decimated to about this many samples
            (their cost is then evaluated on the full data).

    Fitted attributes: ``theta_`` (p,), ``x0_`` list of (nx,), ``cost_`` (0.5 sum of squared
    weighted residuals), ``jac_`` (m, q) over the free parameters then the initial states,
    ``residual_`` (m,), ``std_`` (p,) parameter standard deviations (0 for fixed ones),
    ``starts_`` list of :class:`StartResult`, ``n_estimated_`` (free parameters + initial states),
    ``weights_`` (ny,), ``seconds_``.
    """

    def __init__(self, model: OEModel, starts: int = 4, seed: int = 0,
                 theta0: Array | None = None, extra_starts: Sequence[Array] = (),
                 weights: Array | None = None, max_nfev: int | None = None,
                 progress: Progress | None = None, screen_nfev: int = 30,
                 screen_samples: int = 3000) -> None:
        self.model = model
        self.starts = max(1, int(starts))
        self.seed = seed
        self.theta0 = theta0
        self.extra_starts = list(extra_starts)
        self.weights = weights
        self.max_nfev = max_nfev
        self.screen_nfev = screen_nfev
        self.screen_samples = screen_samples
        self.progress = progress

    def _usable(self, theta: Array) -> bool:
        """A start is usable when its linear part is finite, not unstable (eigenvalues of A with
        real part <= 0) and its B is not all zero."""
        try:
            A, B, _ = self.model.structure.matrices(theta[: self.model.n_struct])
        except (np.linalg.LinAlgError, ValueError):
            return False
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))) or not np.any(B):
            return False
        scale = float(np.max(np.abs(A))) if A.size else 0.0
        return bool(np.max(np.linalg.eigvals(A).real, initial=-np.inf) <= 1e-9 * scale)

    def _say(self, msg: str) -> None:
        if self.progress is not None:
            self.progress(msg)

    def _unpack(self, z: Array, theta_fixed: Array, nseg: int) -> tuple[Array, list[Array]]:
        m = self.model
        nfree = int(m.free.sum())
        theta = theta_fixed.copy()
        theta[m.free] = z[:nfree]
        x0s = [z[nfree + i * m.nx: nfree + (i + 1) * m.nx] for i in range(nseg)]
        return theta, x0s

    def _residual(self, theta: Array, segments: Sequence[Segment], x0s: Sequence[Array],
                  w: Array) -> Array:
        parts = []
        for seg, x0 in zip(segments, x0s, strict=True):
            try:
                with np.errstate(all="ignore"):
                    yh = self.model.simulate(theta, seg, x0)
                parts.append(((seg.y - yh) / w).ravel())
            except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError):
                parts.append(np.full(seg.y.size, _BIG))
        return _clean(np.concatenate(parts))

    def fit(self, segments: Sequence[Segment]) -> OEFit:
        """Fit to ``segments``; returns self.

        Raises:
            FitError: no segments, inconsistent names, or no start gave a finite cost.
        """
        t_start = time.monotonic()
        m = self.model
        if not segments:
            raise FitError("no estimation segments")
        for seg in segments:
            if seg.output_names != m.structure.state_names:
                raise FitError(f"{seg.name}: outputs {list(seg.output_names)} do not match the "
                               f"structure's states {list(m.structure.state_names)}")
            if seg.input_names != m.structure.input_names:
                raise FitError(f"{seg.name}: inputs {list(seg.input_names)} do not match the "
                               f"structure's inputs {list(m.structure.input_names)}")
        if self.weights is None:
            w = np.std(np.vstack([s.y for s in segments]), axis=0)
            w[w == 0] = 1.0
        else:
            w = np.asarray(self.weights, dtype=float)
        self.weights_ = w
        if self.theta0 is not None:
            guess = np.asarray(self.theta0, dtype=float).copy()
        else:
            guess = m.initial()
            guess[: m.n_struct] = m.structure.initial_guess(segments)
        lo = np.array([s.lower for s in m.specs])
        hi = np.array([s.upper for s in m.specs])
        guess = np.clip(guess, lo, hi)
        rng = np.random.default_rng(self.seed)
        starts = [guess]
        for st in self.extra_starts:
            st = np.clip(np.asarray(st, float), lo, hi)
            if self._usable(st) and not np.allclose(st, guess):
                starts.append(st)
        tries = 0
        while len(starts) < self.starts and tries < 50 * self.starts:
            tries += 1
            st = guess.copy()
            for i in range(m.n_struct):
                f = math.exp(rng.uniform(-math.log(3.0), math.log(3.0)))
                st[i] = st[i] * f if st[i] != 0 else rng.normal(0.0, 0.1) * (
                    float(np.max(np.abs(guess[: m.n_struct]))) or 1.0)
            st = np.clip(st, lo, hi)
            if self._usable(st):
                starts.append(st)
        nseg = len(segments)
        free = m.free
        zlo = np.concatenate([lo[free], np.full(nseg * m.nx, -np.inf)])
        zhi = np.concatenate([hi[free], np.full(nseg * m.nx, np.inf)])
        results: list[tuple[Any, Array]] = []
        self.starts_: list[StartResult] = []
        # the first start runs to convergence; the others are screened with a small budget and
        # the best of them is polished only if it beats the first
        screen = self.screen_nfev if self.max_nfev is None else min(self.screen_nfev,
                                                                    self.max_nfev)

        # screening runs on data decimated to about screen_samples samples in all
        q = max(1, sum(sg.n for sg in segments) // max(self.screen_samples, 1))
        screen_segs = [decimate(sg, q) for sg in segments] if q > 1 else list(segments)

        def solve(st: Array, z0: Array, budget: int | None,
                  segs: Sequence[Segment] = segments) -> Any:
            def fun(z: Array) -> Array:
                theta, x0s = self._unpack(z, st, nseg)
                return self._residual(theta, segs, x0s, w)
            return least_squares(fun, z0, bounds=(zlo, zhi), x_scale="jac", method="trf",
                                 max_nfev=budget, ftol=1e-9, xtol=1e-9, gtol=1e-9)

        def cost_on(st: Array, z: Array, segs: Sequence[Segment]) -> float:  # full-rate cost
            theta, x0s = self._unpack(z, st, nseg)
            r = self._residual(theta, segs, x0s, w)
            return 0.5 * float(r @ r)

        ref = math.inf
        for i, st in enumerate(starts):
            t0 = time.monotonic()
            z0 = np.clip(np.concatenate([st[free], *[_x0_guess(s) for s in segments]]), zlo, zhi)
            try:
                same: bool | None = None
                if i == 0:
                    r = solve(st, z0, self.max_nfev)
                    note = ""
                    ref = float(r.cost)
                    usable = True
                else:
                    r = solve(st, z0, screen, screen_segs)
                    note = f" (screened{f' at 1/{q} rate' if q > 1 else ''})"
                    # compared with the first start on the full data
                    r.cost = cost_on(st, r.x, segments) if q > 1 else float(r.cost)
                    same = bool(r.cost <= ref * (1 + 1e-3))
                    usable = False
                    if r.cost < ref * (1 - 1e-4):
                        r = solve(st, r.x, self.max_nfev)  # better than the first: polish
                        note = " (screened, then polished)"
                        same = None
                        usable = True
            except ValueError as exc:
                self._say(f"start {i + 1}/{len(starts)} failed: {exc}")
                continue
            theta, _ = self._unpack(r.x, st, nseg)
            self.starts_.append(StartResult(start=tuple(st.tolist()), theta=tuple(theta.tolist()),
                                            cost=float(r.cost), nfev=int(r.nfev),
                                            status=int(r.status), note=note.strip(" ()"),
                                            same_minimum=same))
            if usable:  # a screened start's residual and Jacobian are not the full data's
                results.append((r, st))
            self._say(f"start {i + 1}/{len(starts)}: cost {r.cost:.6g} after {r.nfev} "
                      f"evaluations{note}, {time.monotonic() - t0:.1f} s")
        if not results:
            raise FitError("no start gave a usable fit")
        best, st = min(results, key=lambda rs: float(rs[0].cost))
        if not np.isfinite(best.cost) or best.cost >= 0.5 * _BIG ** 2:
            raise FitError("simulation diverged from every start (no finite cost)")
        theta, x0s = self._unpack(best.x, st, nseg)
        self.theta_ = theta
        self.x0_ = [np.asarray(x, float) for x in x0s]
        self.cost_ = float(best.cost)
        self.residual_ = np.asarray(best.fun, float)
        self.jac_ = np.asarray(best.jac, float)
        std_free = parameter_std(self.jac_, self.residual_)
        std = np.zeros(len(m.specs))
        std[free] = std_free[: int(free.sum())]
        self.std_ = std
        self.x0_std_ = std_free[int(free.sum()):]
        self.n_estimated_ = int(free.sum()) + nseg * m.nx
        self.segments_ = list(segments)
        self.seconds_ = time.monotonic() - t_start
        return self

    def estimate_x0(self, seg: Segment, theta: Array | None = None) -> Array:
        """Initial state of ``seg`` that best fits it with the parameters fixed, shape (nx,).

        Only the first ``10 / min|Re(eig A)|`` seconds are used (the initial state's influence
        has decayed by ``e^-10`` after that), at least 200 samples; all of it for integrators.
        """
        th = self.theta_ if theta is None else theta
        w = self.weights_
        try:
            A, _, _ = self.model.structure.matrices(th[: self.model.n_struct])
            slow = float(np.min(np.abs(np.linalg.eigvals(A).real)))
        except (np.linalg.LinAlgError, ValueError):
            slow = 0.0
        n = seg.n
        if slow > 0 and np.isfinite(slow):
            n = int(min(seg.n, max(200, math.ceil(10.0 / (slow * seg.dt)))))
        part = seg if n >= seg.n else replace(seg, t=seg.t[:n], u=seg.u[:n], y=seg.y[:n])

        def fun(x0: Array) -> Array:
            return self._residual(th, [part], [x0], w)
        r = least_squares(fun, _x0_guess(seg), method="trf", x_scale="jac")
        return np.asarray(r.x, float)

    def predict(self, seg: Segment, x0: Array | None = None) -> Array:
        """Simulated outputs of ``seg`` (N, ny); ``x0`` estimated when not given."""
        x = self.estimate_x0(seg) if x0 is None else x0
        return self.model.simulate(self.theta_, seg, x)

    def parameters(self) -> dict[str, float]:
        """Physical parameters by name (structure, effects, derived)."""
        return self.model.parameters(self.theta_)

    def parameter_std(self) -> dict[str, float]:
        """Standard deviation of every estimated model parameter by name."""
        return {n: float(s) for n, s, f in zip(self.model.names, self.std_, self.model.free,
                                                strict=True) if f}
