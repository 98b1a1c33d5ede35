"""Involute spur-gear formulas (pure functions, angles in rad, lengths in any one unit).

Internal gears follow the ISO 21771 sign convention: their tooth count ``z``, reference and
tip diameters and the centre distance of an internal mesh are *negative*, so that one set of
formulas serves both kinds of mesh. ``x`` is the profile-shift (addendum-modification)
coefficient; positive ``x`` thickens the tooth at the reference circle for both kinds.
"""

from __future__ import annotations

import math


def inv(alpha: float) -> float:
    """Involute function ``inv a = tan a - a`` [rad]."""
    return math.tan(alpha) - alpha


def inv_inverse(value: float) -> float:
    """The angle ``a`` in [0, pi/2) with ``inv a = value`` (Newton, to 1e-15 rad)."""
    if value < 0.0:
        raise ValueError(f"inv_inverse: expected a value >= 0, got {value!r}")
    a = (3.0 * value) ** (1.0 / 3.0) if value < 0.5 else math.atan(value)  # inv a ~ a^3/3
    for _ in range(60):
        f = inv(a) - value
        step = f / math.tan(a) ** 2 if a > 0.0 else 0.0
        a -= step
        if abs(step) < 1e-15:
            break
    return a


def reference_centre_distance(z1: int, z2: int, module: float) -> float:
    """Nominal (standard) centre distance ``m (z1 + z2) / 2`` (eq. 3.1; negative if internal)."""
    return module * (z1 + z2) / 2.0


def operating_pressure_angle(a_ref: float, a_op: float, alpha: float) -> float:
    """Operating pressure angle from ``a' cos a' = a cos a`` (eq. 3.9-3.10) [rad].

    Raises:
        ValueError: ``|a cos a / a'| >= 1`` (no such mesh).
    """
    c = a_ref * math.cos(alpha) / a_op
    if not 0.0 < c < 1.0:
        raise ValueError(f"a cos(alpha) / a' = {c:.4f} is not in (0, 1): operating centre "
                         f"distance {abs(a_op)!r} mm too short for nominal {abs(a_ref)!r} mm")
    return math.acos(c)


def shift_sum(z1: int, z2: int, alpha: float, alpha_op: float) -> float:
    """``x1 + x2`` that makes the pair run without backlash at ``alpha_op`` (DIN 3992)."""
    return (inv(alpha_op) - inv(alpha)) * (z1 + z2) / (2.0 * math.tan(alpha))


def centre_distance_from_shifts(z1: int, z2: int, x1: float, x2: float, module: float,
                                alpha: float) -> float:
    """Backlash-free centre distance of a pair with shifts ``x1, x2`` (inverse of
    :func:`shift_sum`; signed)."""
    alpha_op = inv_inverse(inv(alpha) + 2.0 * math.tan(alpha) * (x1 + x2) / (z1 + z2))
    return reference_centre_distance(z1, z2, module) * math.cos(alpha) / math.cos(alpha_op)


def undercut_teeth_limit(x: float, alpha: float, addendum: float = 1.0) -> float:
    """Fewest teeth a rack cutter generates without undercut: ``2 (h_a* - x) / sin^2 a``."""
    return 2.0 * (addendum - x) / math.sin(alpha) ** 2


def tooth_thickness(module: float, x: float, alpha: float) -> float:
    """Circular tooth thickness on the reference circle ``m (pi/2 + 2 x tan a)``."""
    return module * (math.pi / 2.0 + 2.0 * x * math.tan(alpha))


def thickness_at_diameter(z: int, module: float, x: float, alpha: float, d_y: float) -> float:
    """Circular tooth thickness at (signed) diameter ``d_y``: ``d_y (s/d + inv a - inv a_y)``.

    Valid for external (``z > 0``) and internal (``z < 0``, ``d_y < 0``) gears.

    Raises:
        ValueError: ``d_y`` inside the base circle (no involute there).
    """
    d = module * z
    c = d * math.cos(alpha) / d_y
    if not 0.0 < c <= 1.0:
        raise ValueError(f"diameter {d_y!r} is inside the base circle {d * math.cos(alpha)!r}")
    return d_y * (tooth_thickness(module, x, alpha) / d + inv(alpha) - inv(math.acos(c)))


def path_of_contact(ra1: float, rb1: float, ra2: float, rb2: float, a_op: float,
                    alpha_op: float) -> float:
    """Length of the path of contact (signed convention: ``ra2, rb2, a_op`` negative for an
    internal gear): ``sqrt(ra1^2 - rb1^2) +- sqrt(ra2^2 - rb2^2) - |a'| sin a'``.

    For an internal gear the ring's term enters with a minus sign and the centre term with a
    plus sign (``T1 T2 = |a'| sin a'`` lies on the same side).

    Raises:
        ValueError: a tip circle inside its base circle.
    """
    if ra1**2 < rb1**2 or ra2**2 < rb2**2:
        raise ValueError(f"a tip circle lies inside its base circle: r_a = {ra1!r}, {ra2!r}; "
                         f"r_b = {rb1!r}, {rb2!r}")
    g1 = math.sqrt(ra1**2 - rb1**2)
    g2 = math.sqrt(ra2**2 - rb2**2)
    s = abs(a_op) * math.sin(alpha_op)
    if a_op < 0.0:
        return g1 - g2 + s
    return g1 + g2 - s


def contact_ratio(path: float, module: float, alpha: float) -> float:
    """Transverse contact ratio: path of contact / base pitch ``pi m cos a``."""
    return path / (math.pi * module * math.cos(alpha))
