"""Do the estimation and test records agree? A check made after every choice.

A model fitted on one record and scored on another can only be as good as the two records are
alike. When the test record needed systematically more (or less) drive than the estimation
record at the same state — a friction that warmed up in between, a load that changed — no model
fitted on the estimation record alone can know it, and the test figure says more about the
records than about the model. :func:`compare_records` measures it with the final model itself:
the residual of each record set is regressed on the simulated outputs' sensitivity to a bias of
each driving input (a constant one, and one per direction of motion of the member that input
drives: what a changed friction looks like), with HAC standard errors
(:func:`dvt_identify.uncertainty.sandwich_covariance`). The test record *disagrees* when its
bias differs from the estimation record's by more than :data:`Z_LIMIT` standard errors and the
difference explains at least :data:`MIN_SHARE` of the test residual.

Measured on EMPS (estimation ``DATA_EMPS``, test ``DATA_EMPS_PULSES``): the test record needs
about 1 N more force in each direction of travel (a friction ~1 N higher), the estimation
record none; the report says so beside the test figure.

Pure; reads nothing but the segments it is given.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.errors import DataError
from dvt_identify.fit import OEFit
from dvt_identify.simulation import DivergedError
from dvt_identify.uncertainty import sandwich_covariance

Array = NDArray[np.float64]
Z_LIMIT = 4.0
"""Standard errors by which a record's bias must differ from the estimation record's."""
MIN_SHARE = 0.1
"""Least share of the test residual's sum of squares the bias difference must explain."""


@dataclass
class RecordBias:
    """The input biases that best explain one record set's residual.

    Attributes:
        labels: what each bias is (``force +`` / ``force -``: the input's bias while the member
            it drives moves up / down; ``force``: a constant bias).
        value, std: the bias [input unit] and its HAC standard error, each (k,).
        explained: share of the residual's sum of squares the biases explain.
    """

    labels: list[str]
    value: Array
    std: Array
    explained: float


@dataclass
class Agreement:
    """Whether the test records agree with the estimation records (:func:`compare_records`).

    Attributes:
        estimation, test: the biases of each set.
        z: the differences in standard errors, (k,).
        explained: share of the test residual the estimation-to-test difference explains.
        disagree: the verdict.
        statement: one plain sentence for the report.
    """

    estimation: RecordBias
    test: RecordBias
    z: Array
    explained: float
    disagree: bool
    statement: str
    details: dict[str, object] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"disagree": self.disagree, "statement": self.statement,
                "labels": self.test.labels,
                "estimation_bias": self.estimation.value.tolist(),
                "estimation_std": self.estimation.std.tolist(),
                "test_bias": self.test.value.tolist(), "test_std": self.test.std.tolist(),
                "z": self.z.tolist(), "explained_share_of_test_residual": self.explained,
                "z_limit": Z_LIMIT, "min_share": MIN_SHARE}


def driving_inputs(fit: OEFit) -> list[tuple[int, int]]:
    """(input, state it drives most) for every input the structure's ``B`` drives (the state
    whose sign is the direction of motion of the member that input drives)."""
    m = fit.model
    _, B, _ = m.structure.matrices(fit.theta_[: m.n_struct])
    out = []
    for j in range(B.shape[1]):
        col = np.abs(B[:, j])
        if np.any(col > 0):
            out.append((j, int(np.argmax(col))))
    return out


def record_bias(fit: OEFit, segs: Sequence[Segment]) -> RecordBias:
    """The input biases (constant and per direction of motion) that best explain ``fit``'s
    residual on ``segs`` (initial states by the fit's own rule), by linear least squares on
    finite-difference sensitivities, HAC standard errors.

    Raises:
        DataError: no segments or no input the structure drives.
    """
    if not segs:
        raise DataError("record_bias: no segments")
    m = fit.model
    pairs = driving_inputs(fit)
    if not pairs:
        raise DataError("record_bias: the structure drives no input")
    w = fit.weights_
    names = segs[0].input_names
    labels = [f"{names[j]} {d}" for j, _ in pairs for d in ("+", "-")]
    cols: list[list[Array]] = []
    resid: list[Array] = []
    for seg in segs:
        x0 = fit.estimate_x0(seg)
        xs, y0 = m.simulate_states(fit.theta_, seg, x0)
        resid.append(((seg.y - y0) / w).ravel())
        parts = []
        for j, k in pairs:
            scale = float(np.std(seg.u[:, j])) or 1.0
            h = 1e-3 * scale
            s = xs[:, k]
            for mask in (s > 0, s < 0):
                u = seg.u.copy()
                u[:, j] += h * mask
                try:
                    yh = m.simulate(fit.theta_, with_u(seg, u), x0)
                except DivergedError:
                    yh = y0
                parts.append(((yh - y0) / w).ravel() / h)
        cols.append(parts)
    k = len(labels)
    J = np.column_stack([np.concatenate([c[i] for c in cols]) for i in range(k)])
    r = np.concatenate(resid)
    beta, *_ = np.linalg.lstsq(J, r, rcond=None)
    cov = sandwich_covariance(J, r - J @ beta, len(w), [s.n for s in segs])
    rr = float(r @ r) or 1.0
    e = r - J @ beta
    return RecordBias(labels=labels, value=np.asarray(beta, float),
                      std=np.asarray(cov.std, float),
                      explained=float(max(0.0, 1.0 - float(e @ e) / rr)))


def with_u(seg: Segment, u: Array) -> Segment:
    """``seg`` with the inputs ``u`` (N, nu) in place of its own."""
    from dataclasses import replace

    return replace(seg, u=np.ascontiguousarray(u))


def compare_records(fit: OEFit, est: Sequence[Segment], test: Sequence[Segment],
                    unit: str = "") -> Agreement:
    """Compare the input biases of the test records with the estimation records' under the
    final model ``fit`` (module docstring).

    Raises:
        DataError: no segments, or no input the structure drives.
    """
    est = list({id(s): s for s in est}.values())  # a segment once, first-seen order
    be = record_bias(fit, est)
    bt = record_bias(fit, test)
    d = bt.value - be.value
    se = np.sqrt(be.std ** 2 + bt.std ** 2)
    z = np.where(se > 0, d / np.where(se > 0, se, 1.0), 0.0)
    # what the difference explains of the test residual: the test bias minus the estimation's
    # applied to the test record's sensitivities (refit restricted to d)
    explained = _explained_by(fit, test, d)
    disagree = bool(np.any(np.abs(z) > Z_LIMIT) and explained >= MIN_SHARE)
    u = f" {unit}" if unit else ""
    # the extra drive the test record needed beyond the estimation record's, under the final
    # model: minus the input bias that makes the model reproduce it
    need = -d
    parts = ", ".join(f"{n:+.3g}{u} while {lab[-1]} on {lab[:-2]} (z = {-zz:+.1f})"
                      for lab, n, zz in zip(bt.labels, need, z, strict=True))
    parts = parts.replace("while + on", "moving up on").replace("while - on", "moving down on")
    # per driving input: read as a dry friction (more resistance both ways) and a constant
    # force: need(+) = dFc + f0, need(-) = -dFc + f0
    reading = []
    for i in range(0, len(need), 2):
        dfc, f0 = 0.5 * (need[i] - need[i + 1]), 0.5 * (need[i] + need[i + 1])
        reading.append(f"a dry friction {dfc:+.3g}{u} and a constant force {f0:+.3g}{u} on "
                       f"{bt.labels[i][:-2]}")
    if disagree:
        st = (f"The test record disagrees with the estimation record: under the final model it "
              f"needed an extra drive of {parts}, which explains {100 * explained:.2g} % of "
              f"its residual (read as {'; '.join(reading)}, against the estimation record); a "
              "model fitted on the estimation record alone cannot know such a change, so the "
              "test figure reflects the records as much as the model.")
    else:
        st = (f"The test record agrees with the estimation record within the checks (extra "
              f"drive {parts}; the difference explains {100 * explained:.2g} % of the test "
              f"residual).")
    return Agreement(estimation=be, test=bt, z=np.asarray(z, float), explained=explained,
                     disagree=disagree, statement=st)


def _explained_by(fit: OEFit, segs: Sequence[Segment], d: Array) -> float:
    """Share of ``fit``'s residual on ``segs`` removed by adding the biases ``d`` (the
    simulation rerun with them)."""
    tot = 0.0
    rem = 0.0
    m = fit.model
    w = fit.weights_
    pairs = driving_inputs(fit)
    for seg in segs:
        x0 = fit.estimate_x0(seg)
        xs, y0 = m.simulate_states(fit.theta_, seg, x0)
        u = seg.u.copy()
        i = 0
        for j, k in pairs:
            s = xs[:, k]
            u[:, j] += d[i] * (s > 0) + d[i + 1] * (s < 0)
            i += 2
        try:
            yb = m.simulate(fit.theta_, with_u(seg, u), x0)
        except DivergedError:
            continue
        r0 = ((seg.y - y0) / w).ravel()
        r1 = ((seg.y - yb) / w).ravel()
        tot += float(r0 @ r0)
        rem += float(r1 @ r1)
    return max(0.0, 1.0 - rem / tot) if tot > 0 else math.nan
