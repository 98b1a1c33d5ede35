"""A design check: what was checked, with which numbers, and whether it passed."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Check:
    """One pass/fail check.

    Attributes:
        id: stable identifier (``stage1.assembly``).
        title: what is checked. criterion: the rule, with its formula.
        passed: the verdict. detail: the numbers that decided it, as one line.
        values: the same numbers, machine-readable.
    """

    id: str
    title: str
    criterion: str
    passed: bool
    detail: str
    values: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"id": self.id, "title": self.title, "criterion": self.criterion,
                "passed": self.passed, "detail": self.detail, "values": self.values}
