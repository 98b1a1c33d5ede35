"""The peer of ``dvt-bench identify --compare``: a multiple-shooting fit of the same grey box
(CasADi + IPOPT), run in the same benchmark run on the same recordings.

The model is the description's own (pure: no ROS):

- the structure ``M w' = -D w + Q u + sum_e c_e tau_e`` with ``M``, ``D`` and ``Q`` built from
  the description's ``mass``, ``damping`` and ``input_matrix`` entries
  (:class:`dvt_identify.structures.ParamMatrix`, the identifier's own parser; the entries are
  linear in the parameters, so the symbolic matrices are ``const + sum_k dM/dtheta_k theta_k``);
- its model effects, built by the description (:meth:`Description.make_model_effects`): the
  band engagement lags (``tau u_eff' = u - u_eff``, exact steps, ``u_eff`` starts at ``u[0]``
  as in :class:`dvt_identify.effects.brakes.BrakeEngagement`) and the bands (dry friction on
  the ring's member ``c`` with capacity ``band_gain * max(u_eff, 0)``,
  :class:`~dvt_identify.effects.brakes.BrakeLockup`);
- the friction it is told: the description's ``coulomb_friction`` candidates when the
  recording's ``truth.yaml`` lists ``coulomb_friction`` among the plant's hidden effects
  (``-Fc sign(s) - offset`` on the member, :class:`~dvt_identify.effects.friction.CoulombFriction`,
  with ``|offset| <= Fc``).

The dry signs (bands and Coulomb) are smoothed to ``tanh(s / eps)`` with
:data:`dvt_model.contract.DEFAULT_EPS`, the smoothing of the model node and of the
identifier's smoothed dry laws (:mod:`dvt_identify.effects.friction`); the identifier itself
uses the exact sign with a stick rule, which a gradient-based NLP cannot. Within each 10 ms
shooting interval the speeds are integrated at the recording's sample period with the
L-stable two-stage Rosenbrock method ROS2 (the exact Jacobian of the smoothed dynamics: a
locked band is a stiff mode, ``cap / (eps J_ring)`` about 5000 1/s, where an explicit RK4 at
1 ms diverges), the inputs held over each sample. The objective is the output error of every
sample, each output divided by its standard deviation (the identifier's default weighting);
IPOPT with the exact Hessian solves for the parameters and the node states together, the
continuity of the nodes as equality constraints.

Starts: the description's initial values (the identifier's prior; never the plant's truth),
the node speeds at the measured outputs, the lag states at the inputs lagged with the prior
time constants. Validation: free run of the same smoothed model from the first validation
sample (speeds at the measured ones, lags at the inputs), scored with
:func:`dvt_identify.metrics.figures` like the identifier's rows.

CasADi is an optional benchmark dependency (``requirements-dev.txt``), imported only here and
only when the peer runs (:func:`casadi_available`).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dvt_identify.bench_identify.common import Array, Log, fit_percent, quiet
from dvt_identify.data import Segment
from dvt_identify.description import Description, load_description
from dvt_identify.effects import Effect, ParamSpec
from dvt_identify.effects.brakes import BrakeEngagement, BrakeLockup
from dvt_identify.effects.friction import CoulombFriction
from dvt_identify.errors import BenchError, DescriptionError
from dvt_identify.fit import bound_hit
from dvt_identify.structures import ParamMatrix
from dvt_model.contract import DEFAULT_EPS
from dvt_model.errors import BagError
from dvt_model.presets import safe_load
from dvt_model.recording import read_truth

PEER_METHOD = ("multiple shooting (CasADi + IPOPT, 10 ms nodes, ROS2 steps at the sample "
               "period, exact Hessian) of the same grey box told the friction structure, "
               "dry signs tanh(s/eps); free-run validation from the first validation sample")
"""What the peer is, for the comparison's output."""
NODE_SECONDS = 0.01
"""Shooting interval [s]."""
EPS = DEFAULT_EPS
"""Smoothing speed of the dry signs [rad/s] (the model node's, :mod:`dvt_model.friction`)."""
MIN_TIME_CONSTANT = 1e-4
"""Lower bound of an engagement time constant in the peer [s] (its step divides by it; the
description's bound is 0)."""
TOLD_EFFECTS = ("coulomb_friction",)
"""Hidden effects of ``truth.yaml`` the peer can be told (the description's candidates of
that name are added)."""
MAX_ITER = 200
"""IPOPT's iteration limit."""
JIT_FLAGS = ("-O1",)
"""Flags of the C compiler (``gcc``) that compiles the NLP's functions when there is one."""
_GAMMA = 1.0 + 1.0 / math.sqrt(2.0)  # ROS2: L-stable, order 2


def casadi_available() -> bool:
    """Whether CasADi can be imported (the peer's optional dependency)."""
    try:
        import casadi  # noqa: F401
    except ImportError:
        return False
    return True


def told_effects(bag: Path) -> list[str]:
    """The hidden effects of a simulated recording (its ``truth.yaml`` ``effects`` list,
    without the plant preset's ``none``).

    Raises:
        BenchError: no readable ``truth.yaml``, or an effect the peer cannot model.
    """
    try:
        truth = read_truth(bag)
    except BagError as exc:
        raise BenchError(f"{bag}: peer: cannot read truth.yaml ({exc})") from exc
    if truth is None:
        raise BenchError(f"{bag}: peer: no truth.yaml (the peer is told the plant's friction "
                         "structure)")
    names = [str(e) for e in truth.get("effects", []) or [] if str(e) != "none"]
    bad = [n for n in names if n not in TOLD_EFFECTS]
    if bad:
        raise BenchError(f"{bag}/truth.yaml: effects: the peer models only "
                         f"{', '.join(TOLD_EFFECTS)}, not {', '.join(bad)}")
    return names


@dataclass
class _Parts:
    """The grey box of one description, by parameter index (see :func:`_parts`)."""

    specs: list[ParamSpec]
    M: ParamMatrix
    D: ParamMatrix
    Q: ParamMatrix
    lags: list[tuple[int, int]]  # (input index, parameter index)
    bands: list[tuple[Array, int, int]]  # (member, input index, parameter index)
    coulombs: list[tuple[Array, int, int | None]]  # (member, Fc index, offset index)


def _parts(desc: Description, told: Sequence[str]) -> _Parts:
    """The description's structure, model effects and the told candidates as index tables.

    Raises:
        BenchError: a structure or effect the peer cannot model.
    """
    try:
        data = safe_load(desc.text) or {}
        st = data["structure"]
    except (yaml.YAMLError, KeyError, TypeError) as exc:
        raise BenchError(f"{desc.source}: peer: no structure section ({exc})") from exc
    if st.get("type") != "mechanical" or "stiffness" in st or "members" in st:
        raise BenchError(f"{desc.source}: peer: models only a rigid mechanical structure "
                         f"(mass, damping, input_matrix), not {st.get('type')!r}")
    specs = list(desc.structure.params)
    names = [p.name for p in specs]
    nx, nu = len(desc.state_names), len(desc.input_names)
    try:
        M = ParamMatrix(st["mass"], "structure.mass", names, (nx, nx))
        D = ParamMatrix(st["damping"], "structure.damping", names, (nx, nx))
        Q = ParamMatrix(st["input_matrix"], "structure.input_matrix", names, (nx, nu))
    except (KeyError, DescriptionError) as exc:
        raise BenchError(f"{desc.source}: peer: {exc}") from exc
    effects: list[Effect] = list(desc.make_model_effects())
    effects += [e for e in desc.make_candidates() if e.name in told]
    parts = _Parts(specs, M, D, Q, [], [], [])
    lag_inputs: set[int] = set()
    for e in effects:
        k = len(parts.specs)
        parts.specs.extend(e.params)
        if isinstance(e, BrakeEngagement) and e.index not in lag_inputs:
            lag_inputs.add(e.index)
            parts.lags.append((e.index, k))
        elif isinstance(e, BrakeLockup) and e.member is not None:
            parts.bands.append((np.asarray(e.member, float), e.index, k))
        elif isinstance(e, CoulombFriction) and e.member is not None:
            parts.coulombs.append((np.asarray(e.member, float), k,
                                   k + 1 if len(e.params) > 1 else None))
        else:
            raise BenchError(f"{desc.source}: peer: cannot model {e.label()}")
    return parts


def _sym_matrix(ca: Any, pm: ParamMatrix, theta: Any) -> Any:
    """``pm`` at the symbolic ``theta`` (linear in it: ``const + sum_k d/dtheta_k theta_k``)."""
    d = pm.derivative(int(theta.numel()))
    out = ca.DM(pm.const)
    for k in np.flatnonzero(np.any(d != 0, axis=(1, 2))):
        out = out + ca.DM(d[k]) * theta[int(k)]
    return out


def _step(ca: Any, parts: _Parts, nx: int, nu: int, dt: float) -> Any:
    """One sample period as a CasADi function ``(x, u, theta) -> x_next``; ``x`` holds the
    speeds (nx) then the engagement lags (one per lagged input)."""
    nl = len(parts.lags)
    p = len(parts.specs)
    x = ca.SX.sym("x", nx + nl)
    u = ca.SX.sym("u", nu)
    th = ca.SX.sym("theta", p)
    w, lag = x[:nx], x[nx:]
    ueff = ca.SX(u)
    for j, (i, _) in enumerate(parts.lags):
        ueff[i] = lag[j]
    M = _sym_matrix(ca, parts.M, th)
    D = _sym_matrix(ca, parts.D, th)
    Q = _sym_matrix(ca, parts.Q, th)
    Minv = ca.inv(M) if nx > 2 else ca.vertcat(
        ca.horzcat(M[1, 1], -M[0, 1]), ca.horzcat(-M[1, 0], M[0, 0])) / ca.det(M)

    def f(ws: Any) -> Any:
        force = -ca.mtimes(D, ws) + ca.mtimes(Q, ueff)
        for c, i, k in parts.bands:
            cap = th[k] * ca.fmax(ueff[i], 0.0)
            force += ca.DM(c) * (-cap * ca.tanh(ca.dot(ca.DM(c), ws) / EPS))
        for c, kf, ko in parts.coulombs:
            tau = -th[kf] * ca.tanh(ca.dot(ca.DM(c), ws) / EPS)
            if ko is not None:
                tau = tau - th[ko]
            force += ca.DM(c) * tau
        return ca.mtimes(Minv, force)

    f0 = f(w)
    W = ca.SX.eye(nx) - _GAMMA * dt * ca.jacobian(f0, w)
    Winv = ca.inv(W) if nx > 2 else ca.vertcat(
        ca.horzcat(W[1, 1], -W[0, 1]), ca.horzcat(-W[1, 0], W[0, 0])) / ca.det(W)
    k1 = ca.mtimes(Winv, f0)
    k2 = ca.mtimes(Winv, f(w + dt * k1) - 2 * k1)
    w_next = w + dt * (1.5 * k1 + 0.5 * k2)
    lag_next = []
    for j, (i, k) in enumerate(parts.lags):
        a = ca.exp(-dt / th[k])
        lag_next.append(a * lag[j] + (1 - a) * u[i])
    return ca.Function("step", [x, u, th], [ca.vertcat(w_next, *lag_next)])


def _lagged(u: Array, parts: _Parts, theta: Array, dt: float) -> Array:
    """The engagement lag states over a record, shape (N, n_lags) (exact steps from ``u[0]``)."""
    out = np.empty((u.shape[0], len(parts.lags)))
    for j, (i, k) in enumerate(parts.lags):
        a = math.exp(-dt / max(float(theta[k]), MIN_TIME_CONSTANT))
        v = float(u[0, i])
        for n in range(u.shape[0]):
            out[n, j] = v
            v = a * v + (1 - a) * float(u[n, i])
    return out


def _scales(parts: _Parts, segs: Sequence[Segment], theta0: Array) -> Array:
    """Per-parameter scale of the NLP's variables: ``|initial|``, else the RMS generalised
    force of the inputs (the scale of a friction force) [force unit]."""
    Qm = parts.Q(theta0)
    force = float(np.sqrt(np.mean(np.concatenate([(s.u @ Qm.T) ** 2 for s in segs]))))
    return np.where(np.abs(theta0) > 0, np.abs(theta0), force or 1.0)


@dataclass
class PeerFit:
    """A fitted peer.

    Attributes:
        parameters: name -> value (the description's names).
        theta: the same, shape (p,).
        seconds, cpu_seconds: the fit (building the NLP and IPOPT) [s].
        status: IPOPT's return status; iterations: its iteration count.
        nodes: shooting nodes over all estimation segments.
        build_seconds: building the NLP (with ``compiled``: compiling it with the C compiler),
            part of ``seconds``.
        at_bounds: parameters at a bound of the description (:func:`dvt_identify.fit.bound_hit`,
            the identifier's rule), by name.
    """

    parameters: dict[str, float]
    theta: Array
    seconds: float
    cpu_seconds: float
    status: str
    iterations: int
    nodes: int
    build_seconds: float
    compiled: bool
    at_bounds: list[str]


def fit_peer(est: Sequence[Segment], desc: Description, told: Sequence[str] = (),
             log: Log = quiet) -> tuple[PeerFit, Any]:
    """Fit the grey box to ``est`` by multiple shooting (module docstring).

    Returns:
        The fit and the step function (for :func:`simulate_peer`).

    Raises:
        BenchError: CasADi missing, a model the peer cannot build, or IPOPT failing outright.
    """
    if not casadi_available():
        raise BenchError("peer not run: casadi not installed")
    import casadi as ca

    c0, t0 = time.process_time(), time.perf_counter()
    parts = _parts(desc, told)
    nx, nu, nl = len(desc.state_names), len(desc.input_names), len(parts.lags)
    init = desc.initial_values()
    theta0 = np.array([init.get(p.name, p.initial) for p in parts.specs], float)
    scale = _scales(parts, est, theta0)
    lo = np.array([p.lower for p in parts.specs], float)
    hi = np.array([p.upper for p in parts.specs], float)
    for _, k in parts.lags:
        lo[k] = max(lo[k], MIN_TIME_CONSTANT)
    dts = {round(s.dt, 12) for s in est}
    if len(dts) != 1:
        raise BenchError(f"peer: estimation segments of different sample periods {sorted(dts)}")
    dt = est[0].dt
    L = max(1, round(NODE_SECONDS / dt))
    step = _step(ca, parts, nx, nu, dt)
    std = np.sqrt(np.mean(np.concatenate([(s.y - s.y.mean(axis=0)) ** 2 for s in est]),
                          axis=0))
    wgt = 1.0 / np.where(std > 0, std, 1.0)
    # one interval: L steps from its node, the weighted squared error of its L samples
    x = ca.SX.sym("x", nx + nl)
    U = ca.SX.sym("U", nu, L)
    Y = ca.SX.sym("Y", nx, L)
    th = ca.SX.sym("theta", len(parts.specs))
    xs, sse = x, ca.SX(0)
    for j in range(L):
        sse += ca.sumsqr((Y[:, j] - xs[:nx]) * ca.DM(wgt))
        xs = step(xs, U[:, j], th)
    jit = shutil.which("gcc") is not None
    tb = time.perf_counter()
    tmpdir = tempfile.TemporaryDirectory(prefix="dvt-peer-")
    # the interval and its derivatives (der_options) compiled, about 10x faster than CasADi's
    # interpreter; their files are removed with tmpdir (not by CasADi: still loaded then)
    jopts: dict[str, Any] = {"jit": True, "compiler": "shell", "jit_cleanup": False,
                             "jit_options": {"flags": list(JIT_FLAGS), "verbose": False,
                                             "cleanup": False,
                                             "directory": tmpdir.name + os.sep}}
    jopts["der_options"] = dict(jopts)
    interval = ca.Function("interval", [x, U, Y, th], [xs, sse], jopts if jit else {})

    z = ca.MX.sym("z", len(parts.specs))
    theta = z * ca.DM(scale)
    w_vars, w0, wlo, whi, g = [z], [theta0 / scale], [lo / scale], [hi / scale], []
    obj = ca.MX(0)
    n_samples, nodes = 0, 0
    p_vars: list[Any] = []
    p_vals: list[Array] = []
    for s in est:
        K = (s.n - 1) // L
        if K < 1:
            continue
        X = ca.MX.sym("X", nx + nl, K + 1)
        idx = np.arange(K + 1) * L
        lag0 = _lagged(s.u, parts, theta0, dt)[idx]
        xinit = np.hstack([s.y[idx], lag0]).T
        xlo = np.full(xinit.shape, -np.inf)
        xhi = np.full(xinit.shape, np.inf)
        for j, (i, _) in enumerate(parts.lags):  # u_eff starts at u[0]
            xlo[nx + j, 0] = xhi[nx + j, 0] = float(s.u[0, i])
        Us = np.concatenate([s.u[k * L:(k + 1) * L].T for k in range(K)], axis=1)
        Ys = np.concatenate([s.y[k * L:(k + 1) * L].T for k in range(K)], axis=1)
        # the data are NLP parameters, not constants: the compiled code does not grow with them
        PU, PY = ca.MX.sym("U", nu, K * L), ca.MX.sym("Y", nx, K * L + 1)
        p_vars += [ca.vec(PU), ca.vec(PY)]
        p_vals += [Us.ravel(order="F"), np.hstack([Ys, s.y[K * L][:, None]]).ravel(order="F")]
        ends, sses = interval.map(K)(X[:, :K], PU, PY[:, : K * L], ca.repmat(theta, 1, K))
        last = ca.sumsqr((PY[:, K * L] - X[:nx, K]) * ca.DM(wgt))
        obj = obj + ca.sum2(sses) + last
        g.append(ca.vec(ends - X[:, 1:]))
        w_vars.append(ca.vec(X))
        w0.append(xinit.ravel(order="F"))
        wlo.append(xlo.ravel(order="F"))
        whi.append(xhi.ravel(order="F"))
        n_samples += K * L + 1
        nodes += K + 1
    if not n_samples:
        raise BenchError(f"peer: no estimation segment longer than one {NODE_SECONDS} s "
                         "interval")
    glo, ghi = [np.zeros(int(gi.numel())) for gi in g], [np.zeros(int(gi.numel())) for gi in g]
    # admissible friction (|offset| <= Fc) and a positive definite M (det M > 0)
    for _, kf, ko in parts.coulombs:
        if ko is not None:
            g += [theta[kf] + theta[ko], theta[kf] - theta[ko]]
            glo += [np.zeros(1), np.zeros(1)]
            ghi += [np.full(1, np.inf), np.full(1, np.inf)]
    Msym = _sym_matrix(ca, parts.M, theta)
    det0 = float(np.linalg.det(parts.M(theta0)))
    g.append(ca.det(Msym) / det0)
    glo.append(np.full(1, 1e-3))
    ghi.append(np.full(1, np.inf))
    nlp = {"x": ca.vertcat(*w_vars), "p": ca.vertcat(*p_vars), "f": 0.5 * obj / n_samples,
           "g": ca.vertcat(*g)}
    opts: dict[str, Any] = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                            "ipopt.max_iter": MAX_ITER, "ipopt.hessian_approximation": "exact"}
    try:
        solver = ca.nlpsol("peer", "ipopt", nlp, opts)
        build = time.perf_counter() - tb
        log(f"peer: {nodes} nodes, {len(parts.specs)} parameters, IPOPT "
            f"(NLP built in {build:.1f} s{', compiled' if jit else ''})")
        sol = solver(x0=np.concatenate(w0), p=np.concatenate(p_vals),
                     lbx=np.concatenate(wlo), ubx=np.concatenate(whi),
                     lbg=np.concatenate(glo), ubg=np.concatenate(ghi))
        stats = solver.stats()
    finally:
        tmpdir.cleanup()
    zf = np.asarray(sol["x"][: len(parts.specs)], float).ravel()
    th_fit = zf * scale
    if not np.all(np.isfinite(th_fit)):
        raise BenchError(f"peer: IPOPT returned non-finite parameters ({stats['return_status']})")
    fit = PeerFit(parameters={p.name: float(v) for p, v in zip(parts.specs, th_fit, strict=True)},
                  theta=th_fit, seconds=time.perf_counter() - t0,
                  cpu_seconds=time.process_time() - c0, status=str(stats["return_status"]),
                  iterations=int(stats.get("iter_count", -1)), nodes=nodes,
                  build_seconds=build, compiled=jit,
                  at_bounds=[p.name for p, v in zip(parts.specs, th_fit, strict=True)
                             if bound_hit(p, float(v)) is not None])
    return fit, (step, parts)


def simulate_peer(model: Any, theta: Array, seg: Segment) -> Array:
    """Free run of the peer's model over ``seg`` from its first sample (speeds at the measured
    ones, lags at the inputs), shape (N, nx)."""
    step, parts = model
    nx = seg.y.shape[1]
    x0 = np.concatenate([seg.y[0], [seg.u[0, i] for i, _ in parts.lags]])
    sim = step.mapaccum("free_run", seg.n - 1)
    X = np.asarray(sim(x0, seg.u[:-1].T, np.tile(theta[:, None], (1, seg.n - 1))), float)
    return np.vstack([seg.y[0], X[:nx].T])


def run_peer(est_bag: Path, val_bag: Path, description: str | Description = "dvt",
             log: Log = quiet) -> dict[str, Any]:
    """The peer on one estimation/validation pair: fit on ``est_bag`` told the friction of its
    ``truth.yaml``, free-run validation on ``val_bag``.

    Returns:
        ``{"method", "told", "validation_fit_percent_free_run", "parameters", "fit_seconds",
        "cpu_seconds", "status", "iterations", "nodes", "eps", "build_seconds",
        "compiled", "at_bounds"}`` (``cpu_seconds``: this process's, without the compiler's).

    Raises:
        BenchError: CasADi missing, no ``truth.yaml``, a model the peer cannot build.
        DataError: a recording the description cannot read.
    """
    from dvt_identify.metrics import figures
    from dvt_identify.pipeline import drop_unexcited_model_effects, load_segments

    desc = load_description(description) if isinstance(description, str) else description
    told = told_effects(est_bag)
    est = load_segments([est_bag], desc)
    val = load_segments([val_bag], desc)
    desc, _ = drop_unexcited_model_effects(desc, est)
    log(f"peer: {est_bag.name} -> {val_bag.name}, told {', '.join(told) or 'no friction'}")
    fit, model = fit_peer(est, desc, told, log)
    free = [simulate_peer(model, fit.theta, s) for s in val]
    fig = figures([s.y for s in val], free, len(fit.theta), val[0].output_names)
    return {"method": PEER_METHOD, "told": told,
            "validation_fit_percent_free_run": fit_percent(fig),
            "parameters": fit.parameters, "fit_seconds": fit.seconds,
            "cpu_seconds": fit.cpu_seconds, "status": fit.status,
            "iterations": fit.iterations, "nodes": fit.nodes, "eps": EPS,
            "build_seconds": fit.build_seconds, "compiled": fit.compiled,
            "at_bounds": fit.at_bounds}
