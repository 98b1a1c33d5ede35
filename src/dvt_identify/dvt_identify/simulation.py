"""Simulation of the output-error models: exact ZOH of the linear part, the step loop with
state-dependent member forces, and :class:`OEModel` (a structure plus effects).

Simulation is an exact zero-order-hold discretisation of the linear part (``scipy.linalg.expm``
of ``[[A, I], [0, 0]] dt``) with every effect term evaluated at the start of a step and held over
it. Models whose effects are all exogenous (no state-dependent force) are simulated in modal form
with ``scipy.signal.lfilter`` (vectorised); otherwise a step loop (compiled with numba,
:mod:`dvt_identify.simloop`) applies dry friction with a stick rule: a member speed that would
cross zero within a step is set to zero, and it stays zero while the force needed to hold it is
within the friction capacity.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal
from scipy.linalg import expm

from dvt_identify.data import Segment
from dvt_identify.effects import Effect, ParamSpec, SegmentView
from dvt_identify.errors import DataError, DescriptionError, FitError
from dvt_identify.simloop import loop_members, loop_scalar, smooth_value
from dvt_identify.structures import ModelStructure, output_matrix, output_names

Array = NDArray[np.float64]


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


def zoh_decimate(seg: Segment, q: int) -> Segment:
    """``seg`` at ``1/q`` of its rate, consistent with the zero-order hold of the simulation.

    The model holds ``u[k]`` over the step ``[t_k, t_k + q dt)``, so the decimated input is the
    mean of the ``q`` fine samples of that step (exact for an input that is piecewise constant
    at the fine rate), not a sample of a zero-phase low-passed input: that one is centred on
    ``t_k`` and leads the held input by half a coarse step, which biases ``M`` and ``D`` and
    the lock-up times (measured: 5-9 % on M and D at 1 kHz / 5). The outputs are the centred
    ``q``-sample mean at each kept sample (an anti-alias filter without delay; for an even
    ``q`` the ``q + 1`` samples about it with half weights at the ends); the first is
    the measured sample. A tail shorter than ``q`` samples is dropped. ``q <= 1`` returns
    ``seg``.

    Raises:
        DataError: fewer than 10 samples would remain (naming the segment).
    """
    if q <= 1:
        return seg
    if seg.n // q < 10:
        raise DataError(f"{seg.name}: too little data to decimate by {q}: {seg.n} samples")
    n = (seg.n // q) * q
    u = seg.u[:n].reshape(n // q, q, seg.u.shape[1]).mean(axis=1)
    # centred: an odd q averages q samples about the kept one; an even q the q + 1 samples
    # about it with half weights at both ends (a q-sample box centred on the kept sample:
    # ``np.ones(q) / q`` with an even q is centred half a fine step early, a lag of dt / 2 in
    # the decimated outputs only - measured at 250 Hz / 2: a 2-ms delay the full-rate
    # validation data do not have, so the estimation data asked for a measurement delay the
    # validation data refused)
    kern = np.ones(q) / q if q % 2 else np.concatenate([[0.5], np.ones(q - 1), [0.5]]) / q
    y = np.empty((n // q, seg.y.shape[1]))
    for j in range(seg.y.shape[1]):
        y[:, j] = np.convolve(seg.y[:, j], kern, mode="same")[:n:q]
    y[0] = seg.y[0]
    ang = None if seg.angles is None else seg.angles[:n:q].copy()
    return replace(seg, t=seg.t[:n:q].copy(), u=np.ascontiguousarray(u), y=y, dt=seg.dt * q,
                   angles=ang,
                   notes=(*seg.notes, f"decimated by {q} to {1.0 / (seg.dt * q):g} Hz "
                                      f"(input held: step means)"))


class DivergedError(FitError, ValueError):
    """The simulation cannot be run at these parameters (a singular or non-finite linear
    part); fits take it as a penalty, scoring as a sensitivity that carries no information.
    A ``ValueError`` too: callers that map a failed simulation to a penalty by catching
    ``ValueError`` (:mod:`dvt_identify.drift`) keep doing so."""


SmoothLaw = tuple[int, float, float, float]
"""A coded smooth member force ``(kind, p0, p1, p2)`` (:mod:`dvt_identify.simloop`)."""


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
        smooth: (member c, law) pairs: force ``g(c.x)`` with the law coded
            ``(kind, p0, p1, p2)``.
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
    spar = np.array([[float(law[1]), float(law[2]), float(law[3])] for _, law in smooth],
                    dtype=np.float64).reshape(ns, 3)
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
        extra0 = sum(smooth_value(int(k), float(p[0]), float(p[1]), float(p[2]), 0.0)
                     * float(c[0])
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
            fixed.update(e.fixed_names())
        names = [s.name for s in specs]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise DescriptionError(f"duplicate parameter names: {', '.join(dup)}")
        self.specs = tuple(specs)
        self.names = tuple(names)
        self.free = np.array([n not in fixed for n in names], dtype=bool)
        self.n_struct = len(structure.params)
        self.nonlinear = any(e.state_dependent for e in self.effects)
        self.C = output_matrix(structure)
        self.output_names = output_names(structure)

    @property
    def nx(self) -> int:
        """Number of states (= outputs unless the structure has hidden states)."""
        return len(self.structure.state_names)

    @property
    def ny(self) -> int:
        """Number of outputs."""
        return len(self.output_names)

    def initial(self) -> Array:
        """Initial values of every parameter, shape (p,)."""
        return np.array([s.initial for s in self.specs], dtype=float)

    def effect_params(self, theta: Array) -> list[Array]:
        """Each effect's slice of ``theta``."""
        return [theta[s] for s in self._slices]

    def simulate(self, theta: Array, seg: Segment, x0: Array) -> Array:
        """Simulated outputs, shape (N, ny) (see :meth:`simulate_states`)."""
        return self.simulate_states(theta, seg, x0)[1]

    def simulate_states(self, theta: Array, seg: Segment, x0: Array) -> tuple[Array, Array]:
        """Simulated states (N, nx) and outputs (N, ny) for parameters ``theta`` and initial
        state ``x0`` (nx,); ``y = C x`` then the effects' output maps.

        Raises:
            FitError: ``theta`` or ``x0`` has the wrong length.
        """
        if theta.shape != (len(self.specs),):
            raise FitError(f"theta: expected shape ({len(self.specs)},), got {theta.shape}")
        if np.shape(x0) != (self.nx,):
            raise FitError(f"x0: expected shape ({self.nx},), got {np.shape(x0)}")
        A, B, F, Ad, Gd = self._linear(theta, seg.dt)
        ps = self.effect_params(theta)
        u = seg.u
        for e, p in zip(self.effects, ps, strict=True):
            ut = e.input_transform(p, u, seg.dt)
            if ut is not None:
                u = ut
        # effects see the transformed inputs (a brake's capacity follows its engagement lag)
        view = SegmentView(seg.dt, u, seg.y, seg.angles)
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
        d = w @ Gd.T
        if smooth or dry:
            x = simulate_loop(A, Ad, Gd, F, w, d, np.asarray(x0, float), smooth, dry)
        else:
            x = simulate_linear(Ad, d, np.asarray(x0, float))
        y = x if self.C is None else x @ self.C.T
        for e, p in zip(self.effects, ps, strict=True):
            yt = e.output_transform(p, y, seg.dt)
            if yt is not None:
                y = yt
        return x, y

    def _linear(self, theta: Array, dt: float) -> tuple[Array, Array, Array, Array, Array]:
        """``A``, ``B``, ``F`` of the structure at ``theta`` and the ZOH ``Ad``, ``Gd`` at ``dt``.

        Raises:
            DivergedError: a singular or non-finite linear part (e.g. a mass matrix made singular
                or indefinite by a finite-difference step or a solver's trial point), naming
                the structure parameters: a caller fitting or scoring takes it as a
                divergence (a penalty), never as a crash in the linear algebra.
        """
        A = B = F = Ad = Gd = np.zeros((0, 0))
        why = ""
        try:
            A, B, F = self.structure.matrices(theta[: self.n_struct])
            if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))
                    and np.all(np.isfinite(F))):
                why = "A, B or F is not finite"
            else:
                with np.errstate(all="ignore"):
                    Ad, Gd = zoh(A, dt)
                if not (np.all(np.isfinite(Ad)) and np.all(np.isfinite(Gd))):
                    why = f"e^(A dt) at dt = {dt:g} s is not finite"
        except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError) as exc:
            why = f"{type(exc).__name__}: {exc}"
        if why:
            values = ", ".join(f"{n} = {float(v):.6g}" for n, v in
                               zip(self.names[: self.n_struct], theta[: self.n_struct],
                                   strict=True))
            raise DivergedError(f"simulation diverged: the linear part {why} ({values})")
        return A, B, F, Ad, Gd

    def parameters(self, theta: Array) -> dict[str, float]:
        """Physical parameters of the structure, every effect parameter and derived figures."""
        out = dict(self.structure.physical(theta[: self.n_struct]))
        allv = {n: float(v) for n, v in zip(self.names, theta, strict=True)}
        for e, p in zip(self.effects, self.effect_params(theta), strict=True):
            out.update({s.name: float(v) for s, v in zip(e.params, p, strict=True)})
        for e in self.effects:
            out.update(e.derived({**allv, **out}))
        return out
