"""How much the test figure depends on the estimation data it came from (pure).

A test figure is one number from one fit. On an integrating system (a position driven by a
force) a fraction of a unit of drive becomes a drift that grows over the record, and parameters
fitted on another part of the same estimation data can score very differently on the same test
record: on EMPS the chosen structure scores 4.6 to 16.5 mm over halves and quarters of the
estimation record (``examples/emps/README.md``, ``docs/results/emps.json``
``benchmark.part_fits``). A figure printed without that spread overstates what it shows.

:func:`figure_spread` refits the final model on each contiguous half of every segment it was
fitted on (:func:`dvt_identify.series.block_split`), warm from its optimum with its weights and
initial-state rule (one start, as cross-validation's fold fits,
:func:`dvt_identify.stages.fold_fits`), and scores each refit on the test records exactly as the
test figure is scored (:func:`dvt_identify.series.predict_test`). No choice uses it: the report
prints it beside the test figure, with the final model's own figure.

The linear reference gets the same treatment when there is one: refined on each half from its
own model (:meth:`dvt_identify.reference.LinearReference.refit`, its order kept) and scored on
the test records like its test figure. A spread is then read against the reference's: on EMPS
the linear reference's halves score 7.6 and 16.4 mm beside its 5.3, wider than the physical
model's 7.1 and 12.2 beside 4.6 (``docs/results/emps.json`` ``test_spread``): the test figure
of either depends on which part of the record it was fitted on, the physical model's less.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from dvt_identify.data import Segment
from dvt_identify.errors import DataError, DvtIdentifyError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.linref import reference_data
from dvt_identify.metrics import Figures, figures
from dvt_identify.reference import LinearReference
from dvt_identify.series import block_split, predict_test
from dvt_identify.stages import fold_fits

PARTS = 2
"""Contiguous parts of each estimation segment the final model is refitted on."""


@dataclass
class FigureSpread:
    """The test figures of the final model refitted on each part of its estimation data.

    Attributes:
        output_names: the outputs (ny).
        final: the final model's own test figures.
        parts: per part (``first half``, ``second half``), the refit's test figures.
        reference: the linear reference's own test figures (``None``: no reference).
        reference_parts: per part, the reference refined on it: its test figures, or why it
            has none (a refinement that failed, a model that cannot be simulated on the test
            records).
        statement: one line for the report's summary.
    """

    output_names: tuple[str, ...]
    final: Figures
    parts: list[tuple[str, Figures]] = field(default_factory=list)
    reference: Figures | None = None
    reference_parts: list[tuple[str, Figures | str]] = field(default_factory=list)
    statement: str = ""

    def rmse_range(self, j: int) -> tuple[float, float]:
        """Smallest and largest test RMSE of output ``j`` over the parts and the final model."""
        v = [self.final.rmse[j], *(f.rmse[j] for _, f in self.parts)]
        return min(v), max(v)

    def reference_rmse_range(self, j: int) -> tuple[float, float] | None:
        """The same for the linear reference (its scored parts); ``None`` without one."""
        if self.reference is None:
            return None
        v = [self.reference.rmse[j], *(f.rmse[j] for _, f in self.reference_parts
                                       if isinstance(f, Figures))]
        return min(v), max(v)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        out: dict[str, object] = {
            "role": "the final model refitted on each half of its estimation data (warm "
            "from its optimum) and scored on the test records like the test figure; the "
            "linear reference refined on the same halves (warm, its order kept) and scored "
            "like its test figure; no choice uses it",
            "final": self.final.as_dict(),
            "parts": [{"part": name, **fig.as_dict()} for name, fig in self.parts],
            "rmse_range": {n: list(self.rmse_range(j))
                           for j, n in enumerate(self.output_names)},
            "statement": self.statement}
        if self.reference is not None:
            out["reference"] = self.reference.as_dict()
            out["reference_parts"] = [
                {"part": name, **f.as_dict()} if isinstance(f, Figures)
                else {"part": name, "not_scored": f} for name, f in self.reference_parts]
            out["reference_rmse_range"] = {
                n: list(self.reference_rmse_range(j) or ())
                for j, n in enumerate(self.output_names)}
        return out


def _names(parts: int) -> list[str]:
    return (["first half", "second half"] if parts == 2
            else [f"part {k + 1} of {parts}" for k in range(parts)])


def figure_spread(final: OEFit, test: Sequence[Segment], init_window: int = 0,
                  parts: int = PARTS, reference: LinearReference | None = None
                  ) -> FigureSpread:
    """The final model's test figure beside those of its refits on each part of its estimation
    data, and the linear reference's likewise (module docstring).

    Args:
        final: the fitted final model (its ``segments_``, ``theta_``, ``weights_``).
        test: the test segments, read after every choice.
        init_window: the test figure's initial-state rule (0: each whole segment).
        parts: contiguous parts per estimation segment (>= 2).
        reference: the fitted linear reference (fitted on the same estimation data,
            :func:`dvt_identify.linref.fit_reference`), or ``None``.

    Raises:
        DataError: ``parts`` < 2, no test segments, or a segment too short for the parts.
        FitError: a refit failed (naming the part).
    """
    if parts < 2:
        raise DataError(f"test spread: parts: expected >= 2, got {parts}")
    if not test:
        raise DataError("test spread: no test segments")
    w = max(0, int(init_window))
    names = tuple(test[0].output_names)
    ys = [s.y[w:] for s in test]

    def score(fit: OEFit) -> Figures:
        preds = [predict_test(fit, s, w) for s in test]
        return figures(ys, [p[w:] for p in preds], fit.n_estimated_, names)

    blocks = block_split(final.segments_, parts)
    # each part's refit is a fold fit that leaves out every other part's blocks
    others = [[i for i, b in enumerate(blocks) if not b.name.endswith(f"@block{k}")]
              for k in range(1, parts + 1)]
    try:
        refits = fold_fits(final, blocks, others)
    except FitError as exc:
        raise FitError(f"test spread: a refit on part of the estimation data failed: {exc}"
                       ) from exc
    out = FigureSpread(output_names=names, final=score(final))
    out.parts = [(label, score(f)) for label, f in zip(_names(parts), refits, strict=True)]
    def score_ref(ref: LinearReference) -> Figures:
        preds = [ref.predict(s, w) for s in test]
        return figures(ys, [p[w:] for p in preds], ref.n_estimated_, names)

    try:
        out.reference = None if reference is None else score_ref(reference)
    except DvtIdentifyError:  # no test figure of its own (the report says why): no spread
        out.reference = None
    if reference is not None and out.reference is not None:
        for label, out_of_part in zip(_names(parts), others, strict=True):
            try:
                part = reference_data([b for i, b in enumerate(blocks)
                                       if i not in out_of_part], init_window)
                out.reference_parts.append((label, score_ref(reference.refit(part))))
            except DvtIdentifyError as exc:
                out.reference_parts.append((label, str(exc)))
    out.statement = _statement(out)
    return out


def _statement(sp: FigureSpread) -> str:
    """The summary line: each output's test RMSE of the final model and of its refits, then
    the linear reference's likewise."""
    def row(f: Figures | str, j: int) -> str:
        return f"{f.rmse[j]:.4g}" if isinstance(f, Figures) else "not scored"

    per = []
    for j, n in enumerate(sp.output_names):
        txt = (f"{n} RMSE {sp.final.rmse[j]:.4g} (final model), "
               + ", ".join(f"{f.rmse[j]:.4g} ({label})" for label, f in sp.parts))
        rr = sp.reference_rmse_range(j)
        if sp.reference is not None and rr is not None:
            txt += (f"; linear reference {sp.reference.rmse[j]:.4g} (as fitted), "
                    + ", ".join(f"{row(f, j)} ({label})" for label, f in sp.reference_parts)
                    + f"; largest: final model {sp.rmse_range(j)[1]:.4g}, linear reference "
                    f"{rr[1]:.4g}")
        per.append(txt)
    why = [f"linear reference on the {label}: {f}" for label, f in sp.reference_parts
           if not isinstance(f, Figures)]
    return ("Test figure's spread over the estimation data: " + "; ".join(per)
            + ": each model refitted on each half of its estimation data (warm from its "
            "optimum), scored like its test figure; how much the figure depends on which data "
            "it was fitted on (no choice uses it)." + (f" Not scored: {'; '.join(why)}."
                                                      if why else ""))
