"""The friction and drag laws under their historical module name.

The laws live in :mod:`dvt_model.laws` (one table: each law once, with its parameters and the
code of the identifier's compiled kernels); this module only names them for older imports.
"""

from __future__ import annotations

from dvt_model.laws import abs_viscous, coulomb, sign_eps, stribeck, viscous, windage

__all__ = ["abs_viscous", "coulomb", "sign_eps", "stribeck", "viscous", "windage"]
