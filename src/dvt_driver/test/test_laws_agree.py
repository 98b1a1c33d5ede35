"""The model node, the identifier's compiled kernels and the plant evaluate one friction law
(:mod:`dvt_model.laws`) with one smoothing: their torques agree on a speed grid through 0."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_driver.plant.hidden import HiddenEffects
from dvt_driver.plant.hidden.effects import StribeckFriction
from dvt_driver.plant.physics import FrictionForces
from dvt_identify import simloop
from dvt_model import laws
from dvt_model.terms import parse_terms

FC, FS, VS, CW = 0.3, 0.2, 1.5, 2e-3
"""Coulomb level [N m], Stribeck excess [N m], Stribeck speed [rad/s], windage [N m s^2]."""
SPEEDS = np.concatenate([np.linspace(-40.0, 40.0, 321), np.linspace(-0.2, 0.2, 161),
                         [-1e-9, 0.0, 1e-9]])


def _plant() -> FrictionForces:
    hidden = HiddenEffects(coulomb={"carrier3": FC},
                           stribeck={"carrier3": StribeckFriction(Fc=0.0, Fs=FS, vs=VS)},
                           windage={"carrier3": CW})
    forces = FrictionForces(hidden, {"carrier3": np.array([0.0, 1.0])}, {"carrier3": 1.0},
                            dt=1e-5)
    return forces


def test_node_identifier_and_plant_share_the_law_and_its_smoothing() -> None:
    plant = _plant()
    eps = float(plant.v_eps[0])
    assert eps == pytest.approx(0.05)  # the plant's default smoothing, above its floor
    node = parse_terms([{"kind": "coulomb", "member": [0, 1], "Fc": FC, "eps": eps},
                        {"kind": "stribeck", "member": [0, 1], "Fs": FS, "vs": VS, "eps": eps},
                        {"kind": "windage", "member": [0, 1], "Cw": CW}])
    for v in SPEEDS.tolist():
        omega = np.array([0.0, v])
        table = (laws.coulomb(v, FC, 0.0, eps) + laws.stribeck(v, FS, VS, eps)
                 + laws.windage(v, CW))
        ident = -(simloop.smooth_value(simloop.COULOMB, FC, eps, 0.0, v)
                  + simloop.smooth_value(simloop.STRIBECK, FS, VS, eps, v)
                  + simloop.smooth_value(simloop.WINDAGE, CW, 0.0, 0.0, v))
        tol = dict(rel=1e-12, abs=1e-15)
        assert -node.extra_force(omega, 0.0)[1] == pytest.approx(table, **tol), v
        assert ident == pytest.approx(table, **tol), v
        assert plant.member_torques(omega)[0] == pytest.approx(table, **tol), v
    # near 0 the sign is smoothed (tanh), not hard: half the level at v = eps * atanh(1/2)
    v = eps * np.arctanh(0.5)
    assert laws.coulomb(v, FC, 0.0, eps) == pytest.approx(0.5 * FC, rel=1e-12)


def test_a_table_law_acts_in_the_plant_through_the_laws_option() -> None:
    from dvt_driver.plant.hidden import parse_hidden

    hidden = parse_hidden({"laws": {"carrier3": [{"law": "stribeck", "Fs": FS, "vs": VS},
                                                 {"law": "coulomb", "Fc": FC}]}}, "t.yaml")
    assert hidden.effect_names() == ["stribeck", "coulomb"] and not hidden.is_clean
    assert parse_hidden(hidden.to_mapping()).laws == hidden.laws  # truth.yaml round trip
    plant = FrictionForces(hidden, {"carrier3": np.array([0.0, 1.0])}, {"carrier3": 1.0},
                           dt=1e-5)
    eps = float(plant.v_eps[0])
    for v in SPEEDS.tolist():
        table = laws.stribeck(v, FS, VS, eps) + laws.coulomb(v, FC, 0.0, eps)
        assert plant.member_torques(np.array([0.0, v]))[0] == pytest.approx(
            table, rel=1e-12, abs=1e-15), v


@pytest.mark.parametrize(("entry", "message"), [
    ({"law": "glue", "Fc": 1.0}, "t.yaml: laws.carrier3[0].law: expected one of"),
    ({"law": "stribeck", "Fs": 0.2}, "t.yaml: laws.carrier3[0].vs: missing"),
    ({"law": "stribeck", "Fs": 0.2, "vs": 0.0}, "t.yaml: laws.carrier3[0].vs: expected a "
                                                "number > 0"),
    ({"law": "coulomb", "Fc": 1.0, "eps": 0.1}, "t.yaml: laws.carrier3[0].eps: unknown key"),
])
def test_a_bad_plant_law_is_named(entry: dict[str, object], message: str) -> None:
    from dvt_driver.errors import HiddenEffectsError
    from dvt_driver.plant.hidden import parse_hidden

    with pytest.raises(HiddenEffectsError, match=message.replace("[", r"\[").replace(
            "]", r"\]")):
        parse_hidden({"laws": {"carrier3": [entry]}}, "t.yaml")
