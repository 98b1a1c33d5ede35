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
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

from dvt_identify.data import Segment, held_inputs
from dvt_identify.discrete import simulate_linear, zoh
from dvt_identify.effects.base import Effect, ParamSpec, PassedOutput, SegmentView
from dvt_identify.errors import DataError, DescriptionError, FitError
from dvt_identify.simloop import loop_members, loop_scalar, smooth_value
from dvt_identify.structures import ModelStructure, output_matrix, output_names

Array = NDArray[np.float64]


def zoh_derivatives(A: Array, dA: Array, dt: float) -> tuple[Array, Array]:
    """Derivatives of the ZOH along each ``dA[k]`` (stacked (K, nx, nx)): ``dAd``, ``dGd``,
    each (K, nx, nx); exact.

    With distinct, well-conditioned eigenvalues of ``A = V diag(l) V^-1`` (the usual case) the
    Daleckii-Krein form ``V (Phi o (V^-1 dA V)) V^-1``, ``Phi`` the divided differences of
    ``exp(l dt)`` (for ``Ad``) and of ``(exp(l dt) - 1) / l`` (for ``Gd``), for every direction
    at once; otherwise the Fréchet derivative of ``[[Ad, Gd], [0, I]] = expm([[A dt, I dt],
    [0, 0]])``, the upper right block of the exponential of ``[[Z, dZ], [0, Z]]``."""
    nx = A.shape[0]
    K = len(dA)
    fast = _zoh_derivatives_eig(A, dA, dt)
    if fast is not None:
        return fast
    X = np.zeros((4 * nx, 4 * nx))
    X[:nx, :nx] = A * dt
    X[:nx, nx: 2 * nx] = np.eye(nx) * dt
    X[2 * nx: 3 * nx, 2 * nx: 3 * nx] = A * dt
    X[2 * nx: 3 * nx, 3 * nx:] = np.eye(nx) * dt
    dAd = np.empty((K, nx, nx))
    dGd = np.empty((K, nx, nx))
    for k in range(K):
        X[:nx, 2 * nx: 3 * nx] = dA[k] * dt
        L = expm(X)[:nx, 2 * nx:]
        dAd[k], dGd[k] = L[:, :nx], L[:, nx:]
    return dAd, dGd


def _zoh_derivatives_eig(A: Array, dA: Array, dt: float) -> tuple[Array, Array] | None:
    """:func:`zoh_derivatives` by the eigen decomposition, or ``None`` when ``A`` is not
    safely diagonalisable (ill-conditioned eigenvectors, eigenvalues within ``1e-6`` of each
    other relative to the largest, or no finite result)."""
    try:
        lam, V = np.linalg.eig(A)
        if np.linalg.cond(V) > 1e6:
            return None
        Vi = np.linalg.inv(V)
    except np.linalg.LinAlgError:
        return None
    z = lam * dt
    scale = max(float(np.max(np.abs(z))), 1.0)
    gap = np.abs(z[:, None] - z[None, :]) + np.eye(len(z)) * scale
    if float(np.min(gap)) < 1e-6 * scale:
        return None
    e = np.exp(z)
    with np.errstate(all="ignore"):
        g = np.where(np.abs(z) > 1e-8, (e - 1.0) / np.where(z == 0, 1.0, z), 1.0 + 0.5 * z)
        gp = np.where(np.abs(z) > 1e-4, (z * e - (e - 1.0)) / np.where(z == 0, 1.0, z * z),
                      0.5 + z / 3.0)
    dz = z[:, None] - z[None, :]
    off = ~np.eye(len(z), dtype=bool)
    phi = np.where(off, (e[:, None] - e[None, :]) / np.where(off, dz, 1.0), np.diag(e))
    psi = np.where(off, (g[:, None] - g[None, :]) / np.where(off, dz, 1.0), np.diag(gp))
    # in units of dt: d(e^{A dt}) = dt V (phi o V^-1 dA V) V^-1; Gd = dt g(A dt)
    E = Vi @ dA @ V  # (K, nx, nx)
    dAd = dt * (V @ (phi * E) @ Vi)
    dGd = dt * dt * (V @ (psi * E) @ Vi)
    if not (np.all(np.isfinite(dAd)) and np.all(np.isfinite(dGd))):
        return None
    if np.iscomplexobj(dAd):
        if (float(np.max(np.abs(dAd.imag), initial=0.0)) > 1e-8 * max(
                float(np.max(np.abs(dAd.real), initial=0.0)), 1e-300)):
            return None
        dAd, dGd = dAd.real, dGd.real
    return np.ascontiguousarray(dAd, dtype=float), np.ascontiguousarray(dGd, dtype=float)


def lag_outputs(y: Array, lag: Sequence[float] | None, dt: float) -> Array:
    """Outputs ``y`` (N, ny) or their tangents (N, ny, P) on a step ``dt`` [s] as the sensors
    see them: column ``j`` ``lag[j]`` [s] earlier (:attr:`dvt_identify.data.Segment.
    output_lag`), by linear interpolation between steps (``lag <= dt``; the first sample has
    no predecessor and stays). ``lag`` ``None`` or all 0: ``y`` itself.

    Raises:
        FitError: a lag longer than the step (it would need more than the previous sample).
    """
    if lag is None or not any(lag):
        return y
    out = np.array(y, dtype=float, copy=True)
    for j, d in enumerate(lag):
        if not d:
            continue
        a = float(d) / dt
        if a > 1.0 + 1e-9:
            raise FitError(f"output {j}: a lag of {d:g} s exceeds the step {dt:g} s")
        out[1:, j] = (1.0 - a) * y[1:, j] + a * y[:-1, j]
    return out


def zoh_decimate(seg: Segment, q: int) -> Segment:
    """``seg`` at ``1/q`` of its rate, consistent with the zero-order hold of the simulation.

    The model holds ``u[k]`` over the step ``[t_k, t_k + q dt)``, so the decimated input is the
    mean of the ``q`` fine samples of that step (exact for an input that is piecewise constant
    at the fine rate), not a sample of a zero-phase low-passed input: that one is centred on
    ``t_k`` and leads the held input by half a coarse step, which biases ``M`` and ``D`` and
    the lock-up times (measured: 5-9 % on M and D at 1 kHz / 5). The outputs are the centred
    ``q``-sample mean at each kept sample (an anti-alias filter without delay; for an even
    ``q`` the ``q + 1`` samples about it with half weights at the ends); the first is
    the measured sample. A ``linear`` input (:attr:`~dvt_identify.data.Segment.input_hold`)
    is averaged from its interval means (:func:`~dvt_identify.data.held_inputs`), the exact
    mean of its line over each coarse step, and the result is held (``input_hold`` ``None``);
    the outputs keep their ``output_lag``. A tail shorter than ``q`` samples is dropped.
    ``q <= 1`` returns ``seg``.

    Raises:
        DataError: fewer than 10 samples would remain (naming the segment).
    """
    if q <= 1:
        return seg
    if seg.n // q < 10:
        raise DataError(f"{seg.name}: too little data to decimate by {q}: {seg.n} samples")
    n = (seg.n // q) * q
    # a linear input's interval means, averaged: the mean over each coarse step
    u = held_inputs(seg)[:n].reshape(n // q, q, seg.u.shape[1]).mean(axis=1)
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
    # the coarse samples are step means, held as they are
    return replace(seg, t=seg.t[:n:q].copy(), u=np.ascontiguousarray(u), y=y, dt=seg.dt * q,
                   angles=ang, input_hold=None,
                   notes=(*seg.notes, f"decimated by {q} to {1.0 / (seg.dt * q):g} Hz "
                                      f"(input held: step means)"))


class DivergedError(FitError, ValueError):
    """The simulation cannot be run at these parameters (a singular or non-finite linear
    part); fits take it as a penalty, scoring as a sensitivity that carries no information.
    A ``ValueError`` too: callers that map a failed simulation to a penalty by catching
    ``ValueError`` (:mod:`dvt_identify.drift`) keep doing so."""


SmoothLaw = tuple[int, float, float, float]
"""A coded smooth member force ``(kind, p0, p1, p2)`` (:mod:`dvt_identify.simloop`)."""


@dataclass
class LoopArrays:
    """The arrays of the compiled step loop (:func:`dvt_identify.simloop.loop_members_sens`)
    for one simulation: smooth forces and dry members (grouped by member, capacities added),
    and for each entry of ``dry`` the group it went to (``group``)."""

    sc: Array
    skind: NDArray[np.int64]
    spar: Array
    sgd: Array
    sfc: Array
    dc: Array
    dcap: Array
    dbrk: Array
    dgdf: Array
    dfcv: Array
    dcfc: Array
    group: list[int] = field(default_factory=list)


def loop_arrays(Gd: Array, F: Array, n: int, smooth: Sequence[tuple[Array, SmoothLaw]],
                dry: Sequence[tuple[Array, Array | float, float]]) -> LoopArrays:
    """Smooth forces and dry members as the kernels take them (``n`` samples; see
    :func:`simulate_loop` for ``smooth`` and ``dry``)."""
    nx = Gd.shape[0]
    groups: dict[tuple[float, ...], list[Any]] = {}
    order: list[int] = []
    for c, cap, brk in dry:
        key = tuple(float(v) for v in c)
        capv: Array | float = np.asarray(cap, float) if np.ndim(cap) else float(cap)
        if key in groups:
            grp = groups[key]
            grp[0] = grp[0] + capv
            grp[1] += brk
            order.append(grp[2])
        else:
            groups[key] = [capv, brk, len(groups)]
            order.append(len(groups) - 1)
    ns = len(smooth)
    sc = (np.array([c for c, _ in smooth], dtype=np.float64).reshape(ns, nx) if ns
          else np.zeros((0, nx)))
    skind = np.array([int(law[0]) for _, law in smooth], dtype=np.int64)
    spar = np.array([law[1:4] for _, law in smooth], dtype=np.float64).reshape(ns, 3)
    sfc = np.ascontiguousarray(sc @ F.T)
    sgd = np.ascontiguousarray(sfc @ Gd.T)
    nd = len(groups)
    dc = (np.array(list(groups), dtype=np.float64).reshape(nd, nx) if nd
          else np.zeros((0, nx)))
    dcap = np.empty((nd, n))
    dbrk = np.empty(nd)
    for g, (capv, b, _) in enumerate(groups.values()):
        dcap[g] = capv
        dbrk[g] = float(b)
    dfcv = np.ascontiguousarray(dc @ F.T)
    dgdf = np.ascontiguousarray(dfcv @ Gd.T)
    dcfc = np.einsum("gx,gx->g", dc, dfcv)
    return LoopArrays(sc, skind, spar, sgd, sfc, dc, dcap, dbrk, dgdf, dfcv, dcfc, order)


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
    la = loop_arrays(Gd, F, n, smooth, dry)
    scalar = loop_scalar.py_func if reference else loop_scalar
    w = np.ascontiguousarray(w, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    if nx == 1:
        # one state: every dry member lumped in generalised coordinates
        cap = np.zeros(n)
        brk = 0.0
        gdf_unit = fmap = 1.0
        for g in range(la.dc.shape[0]):
            c0 = float(la.dc[g, 0])
            cap = cap + abs(c0) * la.dcap[g]
            brk += abs(c0) * float(la.dbrk[g])
            fc = float(F[0, 0]) * c0
            gdf_unit = float(Gd[0, 0]) * fc / c0
            fmap = fc / c0
        extra0 = sum(smooth_value(int(k), float(p[0]), float(p[1]), float(p[2]), 0.0)
                     * float(c[0])
                     for k, p, c in zip(la.skind, la.spar, la.sc, strict=True))
        x = scalar(float(A[0, 0]), float(Ad[0, 0]), w[:, 0].copy(), d[:, 0].copy(),
                   float(x0[0]), la.sc[:, 0].copy(), la.skind, la.spar, la.sgd[:, 0].copy(),
                   bool(dry), np.ascontiguousarray(cap), float(brk), gdf_unit, fmap,
                   float(extra0))
        return np.asarray(x, dtype=float)[:, None]
    return loop_members(np.ascontiguousarray(A, np.float64),
                        np.ascontiguousarray(Ad, np.float64), w, d, np.array(x0, np.float64),
                        la.sc, la.skind, la.spar, la.sgd, la.sfc, la.dc, la.dcap, la.dbrk,
                        la.dgdf, la.dfcv, la.dcfc, reference=reference)


@dataclass
class Prepared:
    """One simulation's parts before the step loop (:meth:`OEModel.prepare`).

    Attributes:
        dt: sample time [s].
        A, B, F, Ad, Gd: the linear part and its ZOH.
        ps: each effect's parameters.
        u: the transformed inputs (N, nu); view: what the effects saw.
        w, d: generalised input (N, nx) and its ZOH response ``w @ Gd.T``.
        forces: (effect index, exogenous force (N,)) of each effect that has one.
        smooth, smooth_of: the smooth member laws and the effect of each.
        dry, dry_of: the dry members (member, capacity, break-away) and the effect of each.
    """

    dt: float
    A: Array
    B: Array
    F: Array
    Ad: Array
    Gd: Array
    ps: list[Array]
    u: Array
    view: SegmentView
    w: Array
    d: Array
    forces: list[tuple[int, Array]]
    smooth: list[tuple[Array, SmoothLaw]]
    smooth_of: list[int]
    dry: list[tuple[Array, Array | float, float]]
    dry_of: list[int]
    out_lag: tuple[float, ...] | None = None


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

    def passing_chaotic(self) -> OEModel:
        """This model with each chaotic output map (:attr:`Effect.chaotic_output`, a load
        rattling in a play) passed as the identity, the parameters unchanged: the model the
        scorer differences (its columns and the model's span), as the fit's tangents pass such
        a map (:mod:`dvt_identify.sensitivity`); the model itself when it has none."""
        if not any(e.chaotic_output for e in self.effects):
            return self
        return OEModel(self.structure, [
            PassedOutput(where=e.where, params=e.params, fixed=e.fixed_names())
            if e.chaotic_output else e for e in self.effects])

    def effect_of(self, j: int) -> tuple[int, int]:
        """The effect that parameter ``j`` (an index into ``theta`` past the structure's)
        belongs to and its place among that effect's parameters."""
        for i, sl in enumerate(self._slices):
            if sl.start <= j < sl.stop:
                return i, j - sl.start
        raise FitError(f"parameter index {j}: not an effect parameter (the structure has "
                       f"{self.n_struct}, the model {len(self.specs)} in all)")

    def chaotic_parameters(self) -> list[int]:
        """Indices into ``theta`` of the chaotic output maps' own parameters."""
        return [j for e, sl in zip(self.effects, self._slices, strict=True)
                if e.chaotic_output for j in range(sl.start, sl.stop)]

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

    def effect_slice(self, i: int) -> slice:
        """Where effect ``i``'s parameters sit in ``theta``."""
        return self._slices[i]

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
        self._check_x0(x0)
        pr = self.prepare(theta, seg)
        if pr.smooth or pr.dry:
            x = simulate_loop(pr.A, pr.Ad, pr.Gd, pr.F, pr.w, pr.d, np.asarray(x0, float),
                              pr.smooth, pr.dry)
        else:
            x = simulate_linear(pr.Ad, pr.d, np.asarray(x0, float))
        return x, self.outputs(pr, x)

    def _check_x0(self, x0: Array) -> None:
        if np.shape(x0) != (self.nx,):
            raise FitError(f"x0: expected shape ({self.nx},), got {np.shape(x0)}")

    def outputs(self, pr: Prepared, x: Array) -> Array:
        """Outputs (N, ny) of states ``x`` (N, nx): ``y = C x`` then the effects' output maps
        at the parameters of ``pr``."""
        return self._outputs(pr.ps, pr.out_lag, pr.dt, x)

    def outputs_of(self, theta: Array, seg: Segment, x: Array) -> Array:
        """Outputs (N, ny) of states ``x`` (N, nx) simulated on ``seg``, with the effects'
        output maps at ``theta`` (p,): for parameters that move no state
        (:meth:`Effect.output_only`), one simulation serves every value of theirs.

        Raises:
            FitError: ``theta`` has the wrong length.
        """
        if theta.shape != (len(self.specs),):
            raise FitError(f"theta: expected shape ({len(self.specs)},), got {theta.shape}")
        return self._outputs(self.effect_params(theta), seg.output_lag, seg.dt, x)

    def _outputs(self, ps: Sequence[Array], out_lag: Sequence[float] | None, dt: float,
                 x: Array) -> Array:
        y = lag_outputs(x if self.C is None else x @ self.C.T, out_lag, dt)
        for e, p in zip(self.effects, ps, strict=True):
            yt = e.output_transform(p, y, dt)
            if yt is not None:
                y = yt
        return y

    def transformed_inputs(self, ps: Sequence[Array], seg: Segment) -> Array:
        """The inputs (N, nu) after every effect's input transform (in order) at the effect
        parameters ``ps``."""
        u = held_inputs(seg)
        for e, p in zip(self.effects, ps, strict=True):
            ut = e.input_transform(p, u, seg.dt)
            if ut is not None:
                u = ut
        return u

    def prepare(self, theta: Array, seg: Segment) -> Prepared:
        """Everything a simulation of ``seg`` at ``theta`` needs before the step loop: the
        linear part and its ZOH, the transformed inputs, each effect's exogenous force,
        smooth law and dry capacity, the generalised input ``w`` and its ZOH response ``d``.

        Raises:
            FitError: ``theta`` has the wrong length.
            DivergedError: the linear part cannot be simulated (:meth:`_linear`).
        """
        if theta.shape != (len(self.specs),):
            raise FitError(f"theta: expected shape ({len(self.specs)},), got {theta.shape}")
        A, B, F, Ad, Gd = self._linear(theta, seg.dt)
        ps = self.effect_params(theta)
        u = self.transformed_inputs(ps, seg)
        # effects see the transformed inputs (a brake's capacity follows its engagement lag)
        view = SegmentView(seg.dt, u, seg.y, seg.angles)
        w = u @ B.T
        forces: list[tuple[int, Array]] = []
        smooth: list[tuple[Array, SmoothLaw]] = []
        smooth_of: list[int] = []
        dry: list[tuple[Array, Array | float, float]] = []
        dry_of: list[int] = []
        brk: dict[tuple[float, ...], float] = {}
        for i, (e, p) in enumerate(zip(self.effects, ps, strict=True)):
            f = e.exogenous_force(p, view)
            if f is not None and e.member is not None:
                w = w + np.outer(f, F @ e.member)
                forces.append((i, np.asarray(f, float)))
            if e.state_dependent and e.member is not None:
                law = e.smooth_law(p)
                if law is not None:
                    smooth.append((e.member, law))
                    smooth_of.append(i)
                b = e.breakaway(p)
                if b:
                    key = tuple(float(v) for v in e.member)
                    brk[key] = brk.get(key, 0.0) + b
                cap = e.dry_capacity(p, view)
                if cap is not None:
                    dry.append((e.member, cap, 0.0))
                    dry_of.append(i)
        if brk and dry:
            used: set[tuple[float, ...]] = set()
            with_brk = []
            for c, cap, _ in dry:
                key = tuple(float(v) for v in c)
                with_brk.append((c, cap, 0.0 if key in used else brk.get(key, 0.0)))
                used.add(key)
            dry = with_brk
        return Prepared(dt=seg.dt, A=A, B=B, F=F, Ad=Ad, Gd=Gd, ps=ps, u=u, view=view, w=w,
                        d=w @ Gd.T, forces=forces, smooth=smooth, smooth_of=smooth_of,
                        dry=dry, dry_of=dry_of, out_lag=seg.output_lag)

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
