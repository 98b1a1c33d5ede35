"""Topic level (issue #10): backlash found by the identifier is pushed to the live model node.

The committed recording ``ident-backlash`` comes from a plant with play in a compliant spline
between carrier 3 and a load that carries the tachometer (hidden preset ``backlash``, its gap,
stiffness, damping and load drawn from the plant seed: ``truth.yaml``, which only the tests
read; declared to nobody). The identifier (the description's full loop, 3 rounds) accepts
``backlash@carrier3(compliant)`` and nothing else, and the push maps it to a ``spline_play``
term on the node's carrier-3 output (no longer ``not_pushed``). A real ``dvt_model_node`` takes
the pushed parameters from a params file; ``dvt-replay`` publishes a slice of a fresh validation
run of the same plant into it, once with the pushed terms and once with the ``effects``
parameter emptied (everything else as pushed): the term alone lowers the live carrier-3
residual.

Tolerance of the pushed gap: 3 reported std of the drawn gap. The load rattling in the play is
chaotic (a change of 1e-9 moves its speed by O(1) seconds later), so the fit's tangents pass the
play as the identity and difference it along its own parameters by a secant over 0.3 of their
values (:data:`dvt_identify.effects.backlash.SECANT_SHARE`), and the reported std adds where
the fit lands with that secant halved and doubled (:meth:`dvt_identify.fit.OEFit.
add_landing_spread`). Before, the long-horizon derivative went into the Jacobian: the refit did
not move the gap from the scorer's grid value (0.04) and every std of the fit came out about
1e6 too small (M11 2e-12 against the baseline's 1.9e-5); the test checks that the structure's
std is the baseline's order again. Measured on the committed draw (gap 0.04158 rad): 0.04099
+- 0.00078 (0.75 std; docs/identification.md section 2).

Live residual: carrier-3 RMS with the term below 0.85 times that without (measured 0.80 on the
committed draw re-recorded with the as-built bands, 0.81 before, 0.69-0.78 on the nominal
plant, over 8 s slices); the sun's residual unchanged within 10 % (the play is on carrier 3's
sensor). About 1.2 min on 2 cores (most of it the
identification). A burst of samples lost in transport re-anchors the node (``gap_reanchor``): before
that rule, a burst of about 0.1 s in the replay with the term left the free run off for the rest
of the slice (sun 5.60 against 2.21 rad/s without, a fresh-clone run of 729be9a).

Transport is a confound, not the property: samples lost on the way change the free run the
two RMS figures come from. The re-recorded draw gives 0.80 without losses (sun 2.171 in both
replays, identical to the offline predictor); one re-anchoring burst moves it up to 0.89
(``scripts/lost_bursts.py``), and a CI run of 39b21d6 on a loaded machine measured 1.04 with
the sun's figure off too (2.195 against 2.171: the with-term replay had lost samples). So each
RMS comes from a replay that reached the node whole (:func:`whole_replay`: the residual stamps
show at most :data:`MAX_MISSING` samples missing and no burst the node re-anchors on); a replay
that did not is repeated, at most :data:`ATTEMPTS` times in all, and the test fails naming the
losses if none did. The assertion itself is never repeated.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from model_listener import ModelListener
from recorded import BAGS, identify_recorded, truth_effects

from dvt_identify.pipeline import model_push
from dvt_model.contract import GAP_REANCHOR_S, MODEL_RESIDUAL

pytestmark = [pytest.mark.ros, pytest.mark.slow]

WINDOW = (0.0, 8.0)
"""Replayed slice of the validation run: start, duration [s] (neutral PRBS and multisine:
carrier 3 reverses many times)."""
SKIP = 200
"""Samples after the replay's first (the anchor) left out of the RMS."""
ATTEMPTS = 3
"""Replays of the slice at most, per configuration, to get one that reached the node whole."""
MAX_MISSING = 40
"""Samples of the 8000 replayed that may be missing from a whole replay (0.5 %); lost
singly or in short runs the free run goes on over them on held inputs (a run of 4 moves the
carrier-3 figure by at most 0.02: ``scripts/lost_bursts.py``)."""


def whole_replay(listener: ModelListener, procs, val: Path) -> tuple[np.ndarray, list]:
    """Speed residual RMS [rad/s] (sun, carrier 3) of a replay of the slice that reached the
    model node whole, and the (missing samples, longest stamp step [s]) of each attempt."""
    seen = []
    for _ in range(ATTEMPTS):
        rms, _ = listener.replay(procs, val, WINDOW, SKIP, positions=False)
        missing, step = listener.delivery()
        seen.append((missing, round(step, 4)))
        if missing <= MAX_MISSING and step < GAP_REANCHOR_S - 0.5e-3:
            return rms, seen
    pytest.fail(f"replay of {val} {WINDOW}: no attempt of {ATTEMPTS} reached the model node "
                f"whole (missing samples, longest stamp step [s]): {seen}")


def test_compliant_backlash_is_pushed_and_lowers_the_live_residual(procs, rclpy_context,
                                                                   tmp_path: Path) -> None:
    result, val = identify_recorded("ident-backlash", tmp_path)
    assert result.config.max_effects >= 3
    assert [d.score.label for d in result.accepted] == ["backlash@carrier3(compliant)"]
    truth = truth_effects(BAGS / "ident-backlash").backlash
    assert truth is not None and truth.where == "carrier3_output"
    push = model_push(result)
    assert not any(s.startswith("backlash") for s in push.skipped), push.skipped
    terms = json.loads(push.parameters["effects"])
    (spline,) = [t for t in terms if t["kind"] == "spline_play"]
    assert spline["output"] == 1  # carrier 3 of the node's (sun_shaft, carrier3)
    # the play the plant drew, within 3 reported std (module docstring)
    std, base = result.final.fit.parameter_std(), result.baseline.fit.parameter_std()
    assert std["M11"] > 0.2 * base["M11"], ("the play collapsed the covariance", std, base)
    assert abs(spline["gap"] - truth.gap) <= 3.0 * std["gap_carrier3"], (spline, truth, std)

    params = tmp_path / "pushed.yaml"
    params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {
        **push.parameters, "params": "physical", "detector.enabled": False}}}))
    listener = ModelListener(rclpy_context, "test_backlash_live")
    model = procs.start("dvt_model_node", "--ros-args", "--params-file", str(params))
    listener.spin_until(lambda: listener.node.count_publishers(MODEL_RESIDUAL) > 0, 30.0,
                        "model node")
    live = json.loads(listener.get(["effects"])[0].string_value)
    assert live == terms, (live, terms)
    with_term, seen_with = whole_replay(listener, procs, val)

    ok, why = listener.set_string("effects", "[]")
    assert ok, why
    without, seen_without = whole_replay(listener, procs, val)
    assert model.poll() is None, procs.log(model)
    print(f"\npushed {terms}; live residual RMS [rad/s] (sun, carrier3): with the term "
          f"{with_term.round(3)}, without {without.round(3)}; replays (missing, longest step "
          f"[s]): with {seen_with}, without {seen_without}")
    assert with_term[1] < 0.85 * without[1], (with_term, without)
    assert with_term[0] == pytest.approx(without[0], rel=0.1), (with_term, without)
