"""Exact kinematics of the carrier-to-ring DVT in rational arithmetic.

The two generalised speeds are ``q = (omega_sun, omega_carrier3)`` [rad/s]. Every member's
speed is a linear form ``a * omega_sun + b * omega_carrier3`` with rational ``a, b``.
Chain: one sun shaft carries the three suns; carrier 1 is splined to ring 2, carrier 2 to
ring 3; carrier 3 is the output. Willis' equation per stage:
``Z_s * omega_s + Z_r * omega_r = (Z_s + Z_r) * omega_c``.

Planet speeds follow the thesis's sign convention: positive opposite to the sun's sense,
i.e. ``planet = -(absolute planet angular velocity)`` (see docs/errata.md). The absolute
speeds are available as ``planetN_abs``.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import numpy as np
from numpy.typing import NDArray

from dvt_model.params import TransmissionParams

LinearForm = tuple[Fraction, Fraction]

MEMBERS = (
    "sun", "ring1", "ring2", "ring3", "carrier1", "carrier2", "carrier3",
    "planet1", "planet2", "planet3",
)
BRAKED_RING = {1: "ring1", 2: "ring2", 3: "ring3"}
"""Gear number -> the ring its band brake holds (ring 2 = carrier 1, ring 3 = carrier 2)."""


@dataclass(frozen=True)
class Kinematics:
    """Speed relations of every member.

    Attributes:
        forms: member name -> (a, b) with ``omega_member = a*omega_sun + b*omega_carrier3``.
    """

    forms: dict[str, LinearForm]

    def vector(self, member: str) -> NDArray[np.float64]:
        """The form of ``member`` as a float array, shape (2,)."""
        a, b = self.forms[member]
        return np.array([float(a), float(b)])

    def gear_ratio(self, gear: int) -> Fraction:
        """Exact input/output speed ratio ``omega_sun / omega_carrier3`` with ``gear``'s ring held.

        Raises:
            ValueError: ``gear`` not in 1..3.
        """
        if gear not in BRAKED_RING:
            raise ValueError(f"gear: expected 1, 2 or 3, got {gear!r}")
        a, b = self.forms[BRAKED_RING[gear]]
        # a*ws + b*wc = 0  ->  ws/wc = -b/a
        return -b / a

    def as_strings(self) -> dict[str, list[str]]:
        """Member -> ``["p/q", "p/q"]`` (JSON friendly)."""
        return {m: [str(a), str(b)] for m, (a, b) in self.forms.items()}


def stage_ratio(sun: int, ring: int) -> Fraction:
    """Ratio of one simple planetary stage with its ring held: ``1 + Z_r / Z_s``."""
    return 1 + Fraction(ring, sun)


def kinematics(params: TransmissionParams) -> Kinematics:
    """Exact speed relations for ``params``' tooth counts."""
    sun: LinearForm = (Fraction(1), Fraction(0))
    c3: LinearForm = (Fraction(0), Fraction(1))

    def ring_of(carrier: LinearForm, k: int) -> LinearForm:
        st = params.stages[k]
        return (
            ((st.sun + st.ring) * carrier[0] - st.sun * sun[0]) / st.ring,
            ((st.sun + st.ring) * carrier[1] - st.sun * sun[1]) / st.ring,
        )

    def planet_abs(carrier: LinearForm, k: int) -> LinearForm:
        st = params.stages[k]
        g = Fraction(st.sun, st.planet)
        return ((1 + g) * carrier[0] - g * sun[0], (1 + g) * carrier[1] - g * sun[1])

    r3 = ring_of(c3, 2)
    c2 = r3
    r2 = ring_of(c2, 1)
    c1 = r2
    r1 = ring_of(c1, 0)
    forms: dict[str, LinearForm] = {
        "sun": sun, "ring1": r1, "ring2": r2, "ring3": r3,
        "carrier1": c1, "carrier2": c2, "carrier3": c3,
    }
    for k, c in enumerate((c1, c2, c3), start=1):
        pa = planet_abs(c, k - 1)
        forms[f"planet{k}"] = (-pa[0], -pa[1])
        forms[f"planet{k}_abs"] = pa
        # spin relative to the carrier (what a planet bearing sees), absolute sign convention
        forms[f"planet{k}_rel"] = (pa[0] - c[0], pa[1] - c[1])
    return Kinematics(forms=forms)
