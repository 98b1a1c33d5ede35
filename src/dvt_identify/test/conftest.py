"""Shared toys of the identifier's tests, handed out as fixtures (this folder is not on
``sys.path`` under ``--import-mode=importlib``, so the test files cannot import a helper module).

The toy is a cart ``M v' = F - Fv v`` (M 2.5 kg, Fv 4 N s/m) under random force steps, its speed
read with 1 % noise and an optional constant sensor offset, described with one candidate,
``sensor_offset``. A second cart runs on a linear axis with its position measured and its speed
hidden (``axis_desc``, ``axis_record``: the EMPS benchmark's kind of output).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from dvt_identify import pipeline
from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.simulation import OEModel

# the seed of each bag name the traced pipeline reads
CART_SEEDS = {"est": 1, "val": 2, "test": 3, "est0": 11, "est1": 12}


def _cart_spec(scale: float | None = None,
               candidates: Sequence[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The cart's description as a fresh dict; ``scale`` sets the speed's ``scale``,
    ``candidates`` its candidates (default: ``sensor_offset`` on the speed)."""
    v: dict[str, Any] = {"name": "v", "topic": "/cart/joint_states", "field": "velocity",
                         "joint": "cart"}
    if scale is not None:
        v["scale"] = scale
    return {
        "name": "cart",
        "inputs": [{"name": "force", "topic": "/cart/drive", "field": "effort",
                    "joint": "cart"}],
        "outputs": [v],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                      "parameters": {"M": {"initial": 2.0, "lower": 0.01},
                                     "Fv": {"initial": 3.0, "lower": 0.0}}},
        "candidates": ([{"effect": "sensor_offset", "where": "v"}] if candidates is None
                       else [dict(c) for c in candidates]),
        "preprocess": {"fit_decimate": 1},
        "fit": {"starts": 1, "refit_starts": 1},
    }


def _cart_desc(scale: float | None = None,
               candidates: Sequence[dict[str, Any]] | None = None) -> Description:
    return parse_description(_cart_spec(scale, candidates), "cart.yaml")


def _cart_record(desc: Description, name: str, seed: int, n: int = 1500, offset: float = 0.0
                 ) -> Segment:
    """The cart (M 2.5, Fv 4) under random force steps, 1 % noise, read with ``offset``
    [m/s]."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-5, 5, n // 50 + 1), 50)[:n]
    t = np.arange(n) * 0.01
    clean = make_segment(name, t, u, np.zeros(n), desc.input_names, desc.output_names)
    y = OEModel(desc.structure).simulate(np.array([2.5, 4.0]), clean, np.zeros(1))
    y = y + offset + 0.01 * rng.standard_normal(y.shape)
    return make_segment(name, t, u, y, desc.input_names, desc.output_names)


# -- a cart on a linear axis, its position measured (the EMPS benchmark's kind of output) ----

AXIS_DT = 0.002  # [s]
AXIS_N = 5000


def _axis_desc(candidates: Sequence[dict[str, Any]],
               model_effects: Sequence[dict[str, Any]] = ()) -> Description:
    """A cart on a linear axis, its position measured, its speed hidden:
    ``q' = v, M v' = F - Fv v + effects``, ``y = q`` [m]; ``model_effects`` declared."""
    return parse_description({
        "name": "cart",
        "inputs": [{"name": "force", "topic": "/c/drive", "field": "effort", "joint": "x"}],
        "outputs": [{"name": "position", "topic": "/c/joint_states", "field": "position",
                     "joint": "x"}],
        "structure": {"type": "mechanical", "members": ["cart"], "mass": [["M"]],
                      "damping": [["Fv"]], "stiffness": [[0.0]], "input_matrix": [[1.0]],
                      "outputs": {"position": "cart_angle"}, "force_unit": "N",
                      "speed_unit": "m/s", "angle_unit": "m",
                      "parameters": {"M": {"initial": 1.0, "lower": 0.001},
                                     "Fv": {"initial": 1.0, "lower": 0.0}}},
        "model_effects": list(model_effects),
        "candidates": list(candidates),
        "fit": {"starts": 1, "refit_starts": 1},
    }, "test")


def _axis_record(seed: int, amplitude: float = 0.0, noise: float = 2e-5,
                 force: Callable[[float, float], float] | None = None,
                 order: float = 4 * np.pi) -> Segment:
    """``2 v' = F - 5 v - g(q)`` with ``g = amplitude sin(order q)`` [N] (a force that depends
    on where the cart is: a cogging or a cable, no named candidate) simulated by the
    identifier's own model (the position force iterated to its fixed point as an input), or
    ``- force(q, v)`` by fine exact steps (:func:`_fine_axis`); the position measured with
    white noise [m]; a filtered random force moves the cart over about 1.5 m."""
    from scipy import signal

    rng = np.random.default_rng(seed)
    t = np.arange(AXIS_N) * AXIS_DT
    sos = signal.butter(2, 2.0, fs=1 / AXIS_DT, output="sos")
    f = (8 * np.sin(2 * np.pi * 0.2 * t + seed)
         + 6 * signal.sosfilt(sos, rng.normal(size=AXIS_N)))
    model = OEModel(_axis_desc([]).structure, [])
    theta, x0 = np.array([2.0, 5.0]), np.zeros(2)
    y = np.zeros((AXIS_N, 1))
    if force is not None:
        y = _fine_axis(f, force)
    for _ in range(12 if amplitude else 1 if force is None else 0):
        extra = amplitude * np.sin(order * y[:, 0])
        y = model.simulate(theta, make_segment("c", t, f - extra, y, ["force"],
                                               ["position"]), x0)
    y = y + noise * rng.normal(size=y.shape)
    return make_segment(f"cart{seed}", t, f, y, ["force"], ["position"])


def _fine_axis(f: np.ndarray, force: Callable[[float, float], float]) -> np.ndarray:
    """``2 v' = f - 5 v - force(q, v)`` from rest, each sample's ``f`` held, 20 exact steps
    of the linear part per sample with ``force`` held over each; positions (N, 1)."""
    from scipy.linalg import expm

    h = AXIS_DT / 20
    a = np.array([[0.0, 1.0], [0.0, -2.5]])
    big = expm(np.block([[a, np.array([[0.0], [0.5]])], [np.zeros((1, 3))]]) * h)
    ad, bd = big[:2, :2], big[:2, 2]
    x = np.zeros(2)
    q = np.zeros(f.size)
    for i in range(f.size):
        q[i] = x[0]
        for _ in range(20):
            x = ad @ x + bd * (f[i] - force(float(x[0]), float(x[1])))
    return q[:, None]


@pytest.fixture(scope="session")
def axis_desc() -> Callable[..., Description]:
    """:func:`_axis_desc`: the position-measured cart's description."""
    return _axis_desc


@pytest.fixture(scope="session")
def axis_record() -> Callable[..., Segment]:
    """:func:`_axis_record`: a record of the position-measured cart."""
    return _axis_record


@pytest.fixture(scope="session")
def cart_spec() -> Callable[..., dict[str, Any]]:
    """``cart_spec(scale=None, candidates=None)``: the cart's description as a fresh dict."""
    return _cart_spec


@pytest.fixture(scope="session")
def cart_desc() -> Callable[..., Description]:
    """``cart_desc(scale=None, candidates=None)``: the cart's description, parsed."""
    return _cart_desc


@pytest.fixture(scope="session")
def cart_record() -> Callable[..., Segment]:
    """``cart_record(desc, name, seed, n=1500, offset=0.0)``: a recording of the cart."""
    return _cart_record


SLIDE_PARAMS = {"M": 2.0, "Fv": 3.0}
"""The slide's mass [kg] and viscous friction [N s/m] (:func:`slide_record`)."""
SLIDE_PRIORS = {"M": 1.2, "Fv": 4.5, "Fc": 0.5}
"""Where the slide's fits start: mass and viscous friction 40 % and 50 % off the truth, the dry
friction half the records' 1 N (no prior equals the simulated truth)."""


def _slide_desc() -> Description:
    """A slide ``M v' = F - Fv v - Fc sign(v)`` with one candidate, Coulomb friction with an
    offset (``Fc`` [N], offset [N]); priors :data:`SLIDE_PRIORS`, off the truth."""
    return parse_description({
        "name": "slide",
        "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "c"}],
        "outputs": [{"name": "v", "topic": "/s/joint_states", "field": "velocity",
                     "joint": "c"}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                      "parameters": {"M": {"initial": SLIDE_PRIORS["M"], "lower": 0.01},
                                     "Fv": {"initial": SLIDE_PRIORS["Fv"], "lower": 0.0}}},
        "candidates": [{"effect": "coulomb_friction", "where": "v", "offset": True,
                        "eps": 0.01}],
    }, "slide.yaml")


def _slide_record(seed: int, fc: float = 1.0, bias: Any = 0.0, n: int = 4000,
                  friction: bool = True) -> tuple[Segment, OEModel]:
    """A record of the slide (:data:`SLIDE_PARAMS`, dry friction ``fc`` [N]) under random
    force steps every 0.4 s, 5 ms samples, speed noise 0.002 m/s; its drive was ``bias`` [N]
    (a scalar or one value per sample) more than the logged force. ``friction`` false: the
    linear slide (M, Fv alone). Returns the record and the model that made it."""
    desc = _slide_desc()
    model = OEModel(desc.structure, desc.make_candidates() if friction else [])
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-8.0, 8.0, n // 80 + 1), 80)[:n]
    t = np.arange(n) * 0.005
    true_u = (u + np.broadcast_to(bias, u.shape))[:, None]
    clean = make_segment(f"s{seed}", t, true_u, np.zeros((n, 1)), desc.input_names,
                         desc.output_names)
    theta = [SLIDE_PARAMS["M"], SLIDE_PARAMS["Fv"], *([fc, 0.0] if friction else [])]
    y = model.simulate(np.array(theta), clean, np.zeros(1))
    y = y + 0.002 * rng.standard_normal(y.shape)
    return make_segment(f"s{seed}", t, u[:, None], y, desc.input_names,
                        desc.output_names), model


@pytest.fixture(scope="session")
def slide_record() -> Callable[..., tuple[Segment, OEModel]]:
    """``slide_record(seed, fc=1.0, bias=0.0, n=4000, friction=True)``: a record of the slide
    with dry friction and the model that made it (the toy of the records' disagreement)."""
    return _slide_record


@pytest.fixture(scope="session")
def slide_start() -> Callable[[bool], np.ndarray]:
    """``slide_start(friction=True)``: the slide fit's start, (M, Fv[, Fc, offset]) from
    :data:`SLIDE_PRIORS`."""
    def start(friction: bool = True) -> np.ndarray:
        head = [SLIDE_PRIORS["M"], SLIDE_PRIORS["Fv"]]
        return np.array(head + ([SLIDE_PRIORS["Fc"], 0.0] if friction else []))
    return start


@pytest.fixture
def traced_pipeline(monkeypatch: pytest.MonkeyPatch, tmp_path: Path
                    ) -> tuple[list[str], dict[str, float], Path]:
    """The cart's description file, and ``pipeline`` with its reads and ``identify`` traced in
    order (``events``). A bag named in ``CART_SEEDS`` reads as the cart recorded with its seed
    and with the offset ``offsets`` gives its name (0 where none). Returns
    ``(events, offsets, path)``."""
    events: list[str] = []
    offsets: dict[str, float] = {}
    path = tmp_path / "cart.yaml"
    path.write_text(yaml.safe_dump(_cart_spec()))

    def load(paths: Sequence[str | Path], desc: Description) -> list[Any]:
        out = []
        for b in paths:
            name = Path(b).name
            events.append(f"read {name}")
            out.append(_cart_record(desc, name, CART_SEEDS[name],
                                    offset=offsets.get(name, 0.0)))
        return out

    real = pipeline.identify

    def identify(est: Sequence[Any], val: Sequence[Any], *a: Any, **k: Any) -> Any:
        events.append("identify: " + ",".join(s.name for s in est) + " | "
                      + ",".join(s.name for s in val))
        res = real(est, val, *a, **k)
        events.append("choices made")
        return res

    monkeypatch.setattr(pipeline, "load_segments", load)
    monkeypatch.setattr(pipeline, "identify", identify)
    return events, offsets, path
