"""Identification report, the plots (PNG): measured vs simulated outputs, residual
correlations, the residual spectrum, candidate scores, and the step and Bode response of the
linear part, in the house style (:mod:`dvt_identify.style`).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify import style
from dvt_identify.loop import IdentificationResult
from dvt_identify.report.data import PEAK_RATIO, STRUCTURED_SHARE, residual_floors
from dvt_identify.simulation import simulate_linear, zoh

Array = NDArray[np.float64]

# ---------------------------------------------------------------------------------------------
# Plots
#
# Drawing cost in matplotlib is mostly per axes, tick and text object, not per point. So the
# plots lay out with fixed margins instead of a second layout pass (``tight_layout``), place
# titles at a fixed height, label about six ticks an axis, let one legend serve the
# cross-correlation panels, draw an overlay only when it differs (final vs baseline), draw long
# series as their per-pixel min/max envelope (every peak stays, see :func:`envelope`), write
# log-axis labels without mathtext, and encode the PNGs with fast zlib settings in a background
# thread while the next figure is drawn (same pixels, somewhat larger files).

SaveFigure = Callable[[Any, Path], Path]
"""Writes (or, in a test, inspects) a figure and returns its path (:class:`_PngWriter`)."""
_DPI = 110
_PNG = {"compress_level": 1}
_SUPERSCRIPT = str.maketrans("0123456789-−", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻⁻")


def _plt() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (imported on first use: no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class _PngWriter:
    """Saves figures: draws in the caller's thread; with ``background`` the PNG encoding (which
    releases the GIL) runs in one worker thread while the next figure is drawn. :meth:`wait`
    returns when every file is written (re-raising a failure)."""

    def __init__(self, background: bool = False) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1) if background else None
        self._jobs: list[Future[None]] = []

    def __call__(self, fig: Any, path: Path) -> Path:
        from matplotlib.image import imsave

        fig.set_dpi(_DPI)
        fig.canvas.draw()
        rgba = np.array(fig.canvas.buffer_rgba())
        _plt().close(fig)
        job = partial(imsave, path, rgba, format="png", dpi=_DPI, pil_kwargs=dict(_PNG))
        if self._pool is None:
            job()
        else:
            self._jobs.append(self._pool.submit(job))
        return path

    def wait(self, timeout: float = 120.0) -> None:
        try:
            for job in self._jobs:
                job.result(timeout=timeout)
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)


def _title(ax: Any, text: str) -> None:
    """Axes title at a fixed height (matplotlib skips its costly search for tick labels that
    could collide with an automatically placed title; these plots have none on top)."""
    ax.set_title(text, y=1.0)


def _margins(fig: Any, left: float = 0.85, right: float = 0.2, top: float = 0.4,
             bottom: float = 0.55, hspace: float = 0.6) -> None:
    """Fixed margins [inch] (like ``tight_layout`` for the labels these plots have) and at most
    about seven (x) or five (y) labelled ticks on linear axes."""
    from matplotlib.ticker import AutoLocator, MaxNLocator

    for ax in fig.axes:
        for axis, nbins in ((ax.xaxis, 7), (ax.yaxis, 5)):
            if isinstance(axis.get_major_locator(), AutoLocator):
                axis.set_major_locator(MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]))
    w, h = fig.get_size_inches()
    rows = max(len(fig.axes), 1)
    ax_h = (h - top - bottom - hspace * (rows - 1)) / rows
    fig.subplots_adjust(left=left / w, right=1 - right / w, top=1 - top / h, bottom=bottom / h,
                        hspace=hspace / max(ax_h, 1e-3))


def _log_label(text: str) -> str:
    r"""``$\mathdefault{2\times10^{-3}}$`` -> ``2×10⁻³`` (plain text: no mathtext parsing)."""
    if not (text.startswith("$\\mathdefault{") and text.endswith("}$")):
        return text
    inner = text[len("$\\mathdefault{"):-2].replace("\\times", "×").replace("\\;", " ")
    out, rest = "", inner
    while "^{" in rest:
        head, tail = rest.split("^{", 1)
        exp, rest = tail.split("}", 1)
        out += head + exp.translate(_SUPERSCRIPT)
    return out + rest


def _plain_log_labels(ax: Any, *, x: bool = False, y: bool = False) -> None:
    """Log/symlog tick labels (after the scale is set) as plain text (``10⁻³``: the scale's own
    formatters, their mathtext turned into Unicode); log axes get minor ticks at 2 and 5 per
    decade."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    for on, axis in ((x, ax.xaxis), (y, ax.yaxis)):
        if not on:
            continue
        for minor in (False, True):
            base = axis.get_minor_formatter() if minor else axis.get_major_formatter()
            fmt = FuncFormatter(lambda v, pos, f=base: _log_label(f(v, pos)))
            fmt.set_locs = base.set_locs  # type: ignore[method-assign]
            (axis.set_minor_formatter if minor else axis.set_major_formatter)(fmt)
            base.set_axis(axis)
        if axis.get_scale() == "log":
            axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))


def envelope(t: NDArray[Any], y: NDArray[Any], bins: int) -> tuple[NDArray[Any], NDArray[Any]]:
    """Min/max envelope of a long series for plotting: at most ``2 * bins`` points.

    ``t``, ``y``: shape (N,). The samples are cut into ``bins`` runs of equal length; each run
    keeps its smallest and its largest sample, in time order, at their own times. Drawn as a
    line at about one run per pixel column, the picture equals that of all N samples (every
    peak stays). Series with at most ``2 * bins`` samples are returned as they are.
    """
    n = y.shape[0]
    if n <= 2 * bins:
        return t, y
    k = -(-n // bins)
    m = -(-n // k)
    pad = np.concatenate([y, np.full(m * k - n, y[-1])]).reshape(m, k)
    base = np.arange(m) * k
    lo = np.minimum(base + np.argmin(pad, axis=1), n - 1)
    hi = np.minimum(base + np.argmax(pad, axis=1), n - 1)
    idx = np.column_stack([np.minimum(lo, hi), np.maximum(lo, hi)]).ravel()
    return t[idx], y[idx]


def plot_fits(result: IdentificationResult, out: Path,
              save: SaveFigure | None = None) -> list[Path]:
    """Measured vs simulated (baseline, final) on validation data, one PNG per output.

    Series longer than the figure is wide are drawn as their per-pixel min/max envelope.
    """
    plt = _plt()
    save = save or _PngWriter()
    paths = []
    names = result.description.output_names
    segs = _val_segments(result)
    both = result.final is not result.baseline
    width_in, bins_total = 11.0, int(11.0 * _DPI)
    total = sum(seg.n for seg in segs) or 1
    offsets, offset = [], 0.0
    for seg in segs:
        offsets.append(offset)
        offset = offset + float(seg.t[-1]) + seg.dt
    unit = result.description.structure.speed_unit
    for j, name in enumerate(names):
        fig, axes = plt.subplots(2, 1, figsize=(width_in, 6.5), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1]})
        for k, seg in enumerate(segs):
            t = seg.t + offsets[k]
            bins = max(bins_total * seg.n // total, 50)
            yb = result.baseline.val_pred[k][:, j]
            yf = result.final.val_pred[k][:, j]
            first = k == 0
            # the predictions under the measured trace (thin, black, on top): a prediction
            # that matches shows as a coloured edge and the measurement stays visible
            axes[0].plot(*envelope(t, yb, bins), **style.before(
                (f"baseline ({result.baseline.val.fit_percent[j]:.1f} %)" if both
                 else f"baseline = final ({result.baseline.val.fit_percent[j]:.1f} %)")
                if first else None))
            if both:
                axes[0].plot(*envelope(t, yf, bins), **style.after(
                    f"final ({result.final.val.fit_percent[j]:.1f} %)" if first else None))
            axes[0].plot(*envelope(t, seg.y[:, j], bins),
                         **style.measured("measured" if first else None))
            axes[1].plot(*envelope(t, seg.y[:, j] - yb, bins), **style.residual(
                "before", ("baseline" if both else "baseline = final") if first else None))
            if both:
                axes[1].plot(*envelope(t, seg.y[:, j] - yf, bins),
                             **style.residual("after", "final" if first else None))
        axes[0].set_ylabel(style.label(name, unit))
        _title(axes[0], f"Validation data: measured vs simulated {name} (fit % in the legend)")
        style.legend_outside(axes[0])
        axes[1].set_ylabel(style.label("measured − simulated", unit))
        axes[1].set_xlabel("time [s] (validation segments back to back)")
        style.legend_outside(axes[1])
        _margins(fig, hspace=0.15, right=style.LEGEND_WIDTH_IN)
        paths.append(save(fig, out / f"fit_{name}.png"))
    return paths


def _val_segments(result: IdentificationResult) -> list[Any]:
    return list(result.val_segments)


def _stems(ax: Any, x: NDArray[Any], y: NDArray[Any], color: str, label: str) -> None:
    """Stem plot (as ``Axes.stem``) from one line collection and one marker line."""
    ax.vlines(x, 0.0, y, colors=color, lw=1.0)
    ax.plot(x, y, "o", color=color, label=label)


def plot_residuals(result: IdentificationResult, out: Path,
                   save: SaveFigure | None = None) -> list[Path]:
    """ACF (with the white bound) and CCF per input (Bartlett and white bounds), validation
    data, baseline and final (one set of stems when the final model is the baseline); one PNG
    per output. The CCF panels share one legend."""
    plt = _plt()
    save = save or _PngWriter()
    paths = []
    both = result.final is not result.baseline
    segs = _val_segments(result) or list(result.est_segments)  # est: cross-validated
    dt = float(segs[0].dt) if segs else None
    b_label = "baseline" if both else "baseline = final"
    for rb, rf in zip(result.baseline.resid_val, result.final.resid_val, strict=True):
        inputs = list(rf.ccf)
        fig, axes = plt.subplots(1 + len(inputs), 1, figsize=(11, 2.6 * (1 + len(inputs))))
        axes = np.atleast_1d(axes)
        for ax in axes[1:-1]:  # the cross-correlation panels share the lag axis
            ax.sharex(axes[-1])
            ax.tick_params(labelbottom=False)
        lags = np.arange(rf.lags + 1)
        _stems(axes[0], lags, rb.acf, style.BEFORE, b_label)
        if both:
            _stems(axes[0], lags + 0.25, rf.acf, style.AFTER, "final")
        axes[0].axhspan(-rf.acf_bound, rf.acf_bound, color=style.BAND,
                        label="99 % per lag (white noise)")
        _title(axes[0], f"{rf.output}: residual autocorrelation (validation); Ljung-Box p "
                f"= {rf.ljung_box_p:.2g} (final)")
        axes[0].set_ylabel(style.label("autocorrelation", style.DIMENSIONLESS))
        axes[0].set_xlabel(style.lag_label(dt))
        style.legend_outside(axes[0])
        cl = np.arange(-rf.lags, rf.lags + 1)
        for i, (ax, name) in enumerate(zip(axes[1:], inputs, strict=True)):
            _stems(ax, cl, rb.ccf[name], style.BEFORE, b_label)
            if both:
                _stems(ax, cl + 0.25, rf.ccf[name], style.AFTER, "final")
            ax.axhspan(-rf.ccf_bound[name], rf.ccf_bound[name], color=style.BAND,
                       label="99 % Bartlett, all lags\n(the test)")
            ax.axhline(rf.ccf_bound_per_lag[name], color=style.BOUND, ls="--", lw=0.8,
                       label="99 % Bartlett, per lag")
            ax.axhline(-rf.ccf_bound_per_lag[name], color=style.BOUND, ls="--", lw=0.8)
            ax.axhline(rf.ccf_bound_white, color="tab:red", ls=":", lw=0.8,
                       label="z/sqrt(N) (white)")
            ax.axhline(-rf.ccf_bound_white, color="tab:red", ls=":", lw=0.8)
            _title(ax, f"cross-correlation residual {rf.output} vs input {name} "
                   f"(lag > 0: residual after input)")
            ax.set_ylabel(style.label("cross-corr.", style.DIMENSIONLESS))
            if i == 0:
                style.legend_outside(ax, title="(all cross-\ncorrelation panels)",
                                     title_fontsize=style.LEGEND_FONTSIZE)
        if len(axes) > 1:
            axes[-1].set_xlabel(style.lag_label(dt))
        _margins(fig, left=0.8, hspace=0.8, bottom=0.5, right=style.LEGEND_WIDTH_IN)
        paths.append(save(fig, out / f"resid_{rf.output}.png"))
    return paths


def plot_spectrum(result: IdentificationResult, out: Path,
                  save: SaveFigure | None = None) -> list[Path]:
    """Welch PSD of the validation residual, baseline vs final (one line when the final model
    is the baseline), one PNG per output."""
    plt = _plt()
    save = save or _PngWriter()
    paths = []
    both = result.final is not result.baseline
    floors = residual_floors(result.final, result.val_segments)
    unit = result.description.structure.speed_unit
    for j, name in enumerate(result.description.output_names):
        fig, ax = plt.subplots(figsize=(11, 4))
        sb, sf = result.baseline.spectrum_val[j], result.final.spectrum_val[j]
        ax.loglog(sb.freq[1:], sb.psd[1:], color=style.BEFORE, lw=0.8,
                  label="baseline" if both else "baseline = final")
        if both:
            ax.loglog(sf.freq[1:], sf.psd[1:], color=style.AFTER, lw=0.8, label="final")
        # the same rule as the report's text (remaining_summary): a marker only for a peak the
        # text calls prominent; otherwise the title says where the largest bin is
        prominent = sf.peak_ratio > PEAK_RATIO and (
            j >= len(floors) or not floors[j].structured_share < STRUCTURED_SHARE)
        if prominent:
            ax.axvline(sf.peak_hz, color="k", ls=":", lw=0.8,
                       label=f"peak {sf.peak_hz:.3g} Hz\n({sf.peak_ratio:.2g} x local median)")
            note = f"peak at {sf.peak_hz:.3g} Hz (final)"
        elif sf.peak_ratio > PEAK_RATIO:
            note = (f"no peak above the sensor noise (final: largest bin {sf.peak_ratio:.2g} x "
                    f"the local median, at {sf.peak_hz:.3g} Hz, residual at the noise floor)")
        else:
            note = (f"no prominent peak (final: largest bin {sf.peak_ratio:.2g} x the local "
                    f"median, at {sf.peak_hz:.3g} Hz)")
        _plain_log_labels(ax, x=True, y=True)
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel(f"PSD [{style.psd_unit(unit)}]")
        ax.set_title(f"{name}: validation residual spectrum (Welch)\n{note}", y=1.0,
                     fontsize=10)
        style.legend_outside(ax)
        _margins(fig, left=0.9, right=style.LEGEND_WIDTH_IN, top=0.6)
        paths.append(save(fig, out / f"spectrum_{name}.png"))
    return paths


_MAX_LABEL = 44
"""Longest candidate label drawn in full on the candidates chart [characters]."""


def plot_candidates(result: IdentificationResult, out: Path,
                    save: SaveFigure | None = None) -> Path | None:
    """Projected scores (R^2, %) of every candidate per round, accepted ones highlighted."""
    if not result.rounds:
        return None
    plt = _plt()
    save = save or _PngWriter()
    accepted = {(d.round, d.score.label) for d in result.accepted}
    longest = max(len(r) for r in result.rounds)
    fig, axes = plt.subplots(len(result.rounds), 1,
                             figsize=(9, 2.6 + (0.35 * longest + 0.4) * len(result.rounds)))
    axes = np.atleast_1d(axes)
    def short(label: str) -> str:  # long labels would squeeze the bars out of the figure
        return label if len(label) <= _MAX_LABEL else label[: _MAX_LABEL - 1] + "…"

    for i, (ax, rnd) in enumerate(zip(axes, result.rounds, strict=True)):
        labels = [short(s.label) for s in rnd][::-1]
        vals = [100 * s.r2 for s in rnd][::-1]
        colors = [style.ACCEPTED if (i + 1, s.label) in accepted else style.OTHER
                  for s in rnd][::-1]
        ax.barh(labels, vals, color=colors)
        # a linear axis over the whole 0-100 % range: a 0.005 % candidate draws as the sliver
        # it is, a round where nothing explains much looks like it; the values are written
        for y, v in enumerate(vals):
            text = f"{v:.3g} %" if v >= 1e-3 else ("0 %" if v <= 0 else "< 0.001 %")
            ax.text(v + 0.8, y, text, va="center", fontsize=7)
        ax.set_xlim(0.0, 100.0)
        _title(ax, f"round {i + 1}")
        ax.set_xlabel(style.label("residual sum of squares explained after projection", "%"))
    fig.suptitle("Candidates scored per round (green: accepted in that round; grey: not)",
                 x=0.02, y=1.0 - 0.12 / fig.get_size_inches()[1], ha="left", va="top",
                 fontsize=11)
    width = max((len(short(s.label)) for r in result.rounds for s in r), default=10)
    _margins(fig, left=min(0.4 + 0.085 * width, 4.5), top=0.8, bottom=0.6, hspace=0.8)
    return save(fig, out / "candidates.png")


def plot_linear(result: IdentificationResult, out: Path,
                save: SaveFigure | None = None) -> Path:
    """Step response and Bode magnitude/phase of the final model's linear part (to the
    measured outputs: ``C`` of a structure with hidden states, else C = I)."""
    plt = _plt()
    save = save or _PngWriter()
    A, B = result.final.linear()
    nx, nu = B.shape
    ins = result.description.input_names
    outs = result.description.output_names
    C = result.final.fit.model.C  # None: C = I; else the measured states of hidden ones
    ny = nx if C is None else C.shape[0]
    eig = np.linalg.eigvals(A)
    if C is not None:  # an angle's integrator (eigenvalue 0) sets no time scale
        eig = eig[np.abs(eig) > 1e-9 * max(float(np.max(np.abs(eig), initial=0.0)), 1e-300)]
    slow = float(np.min(np.abs(eig.real))) if eig.size else 1.0
    fast = float(np.max(np.abs(eig))) if eig.size else 1.0
    tend = 6.0 / max(slow, 1e-6)
    t = np.linspace(0.0, min(tend, 1e4), 600)
    w = np.logspace(np.log10(max(slow, 1e-3) / 20), np.log10(max(fast, 1e-2) * 20), 400)
    fig, axes = plt.subplots(3, 1, figsize=(11, 9))
    Ad, Gd = zoh(A, float(t[1] - t[0]))
    H = _freq_all(A, B, w)  # (len(w), nx, nu)
    if C is not None:
        H = np.einsum("ij,wjk->wik", C, H)
    unit = result.description.structure.speed_unit
    in_units = {sp.name: str(getattr(sp, "unit", "") or "")
                for sp in getattr(result.description, "inputs", ())}
    per = {style.per_input_unit(unit, in_units.get(n, "")) for n in ins}
    resp_unit = per.pop() if len(per) == 1 else style.per_input_unit(unit)
    scale = float(np.max(np.abs(H), initial=0.0))
    silent = []  # inputs without a path through the linear part (e.g. the band brakes)
    for i in range(nu):
        if not np.any(np.abs(H[:, :, i]) > 1e-12 * max(scale, 1e-300)):
            silent.append(ins[i])
            continue
        d = np.tile(Gd @ B[:, i], (t.size, 1))
        yy = simulate_linear(Ad, d, np.zeros(nx))
        if C is not None:
            yy = yy @ C.T
        for j in range(ny):
            c = style.CHANNELS[(i * ny + j) % len(style.CHANNELS)]
            axes[0].plot(t, yy[:, j], color=c, label=f"{ins[i]} -> {outs[j]}")
            Hj = H[:, j, i]
            axes[1].loglog(w / (2 * np.pi), np.abs(Hj), color=c)
            axes[2].semilogx(w / (2 * np.pi), np.degrees(np.unwrap(np.angle(Hj))), color=c)
    _plain_log_labels(axes[1], x=True, y=True)
    _plain_log_labels(axes[2], x=True)
    axes[0].set_title("linear part of the final model: unit-step response"
                      + (f"\n({', '.join(silent)}: no path through the linear part; they act "
                         "through the model's effects)" if silent else ""), y=1.0, fontsize=10)
    axes[0].set_xlabel("time [s]")
    axes[0].set_ylabel(f"step response\n[{resp_unit}]")
    style.legend_outside(axes[0])
    _title(axes[1], "Bode magnitude (colours as above)")
    axes[1].set_ylabel(f"|H| [{resp_unit}]")
    axes[1].set_xlabel("frequency [Hz]")
    _title(axes[2], "Bode phase")
    axes[2].set_ylabel("phase [deg]")
    axes[2].set_xlabel("frequency [Hz]")
    _margins(fig, left=1.0, top=0.6, hspace=0.8, right=style.LEGEND_WIDTH_IN)
    return save(fig, out / "linear_step_bode.png")


def _freq_all(A: Array, B: Array, w: Array) -> NDArray[np.complex128]:
    """Frequency response ``(j w I - A)^-1 B`` of shape (len(w), nx, nu)."""
    nx = A.shape[0]
    M = 1j * w[:, None, None] * np.eye(nx)[None] - A[None]
    return np.asarray(np.linalg.solve(M, np.broadcast_to(B, (w.size, *B.shape))),
                      dtype=np.complex128)


# ---------------------------------------------------------------------------------------------
# Markdown
