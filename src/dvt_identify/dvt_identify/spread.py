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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from dvt_identify.data import Segment
from dvt_identify.errors import DataError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.metrics import Figures, figures
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
        statement: one line for the report's summary.
    """

    output_names: tuple[str, ...]
    final: Figures
    parts: list[tuple[str, Figures]] = field(default_factory=list)
    statement: str = ""

    def rmse_range(self, j: int) -> tuple[float, float]:
        """Smallest and largest test RMSE of output ``j`` over the parts and the final model."""
        v = [self.final.rmse[j], *(f.rmse[j] for _, f in self.parts)]
        return min(v), max(v)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"role": "the final model refitted on each half of its estimation data (warm "
                "from its optimum) and scored on the test records like the test figure; no "
                "choice uses it",
                "final": self.final.as_dict(),
                "parts": [{"part": name, **fig.as_dict()} for name, fig in self.parts],
                "rmse_range": {n: list(self.rmse_range(j))
                               for j, n in enumerate(self.output_names)},
                "statement": self.statement}


def _names(parts: int) -> list[str]:
    return (["first half", "second half"] if parts == 2
            else [f"part {k + 1} of {parts}" for k in range(parts)])


def figure_spread(final: OEFit, test: Sequence[Segment], init_window: int = 0,
                  parts: int = PARTS) -> FigureSpread:
    """The final model's test figure beside those of its refits on each part of its estimation
    data (module docstring).

    Args:
        final: the fitted final model (its ``segments_``, ``theta_``, ``weights_``).
        test: the test segments, read after every choice.
        init_window: the test figure's initial-state rule (0: each whole segment).
        parts: contiguous parts per estimation segment (>= 2).

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
    out.statement = "Test figure's spread over the estimation data: " + "; ".join(
        f"{n} RMSE {out.final.rmse[j]:.4g} (final model), "
        + ", ".join(f"{f.rmse[j]:.4g} ({label})" for label, f in out.parts)
        for j, n in enumerate(names)) + (
        ": the final model refitted on each half of its estimation data, scored like the test "
        "figure; how much the figure depends on which data it was fitted on (no choice uses "
        "it).")
    return out
