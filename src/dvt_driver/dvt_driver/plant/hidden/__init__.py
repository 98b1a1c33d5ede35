"""Hidden effects of the simulated plant: what the identifier has to find (pure, no I/O but files).

The simulated plant (:mod:`dvt_driver.plant.core`) runs the clean ``dvt_model`` physics plus the
effects configured here. The configuration is a YAML mapping in which every effect is optional;
the identifier never reads it. The plant writes it, with its own parameters, as ``truth.yaml``
beside a recording (:meth:`HiddenEffects.to_truth_yaml`).

YAML schema (units SI; every top-level key optional)::

    coulomb:                 # Coulomb friction per member: torque -Fc sign(v) [N m]
      sun: 0.08
    stribeck:                # Stribeck static curve per member [N m, N m, rad/s]
      carrier3: {Fc: 0.10, Fs: 0.30, vs: 1.5}      # optional: delta (shape exponent, default 2)
    windage:                 # quadratic drag per member: torque -c |v| v, c [N m s^2]
      sun: 2.0e-6
    backlash:                # free play between carrier 3 and an output shaft with a load
      where: carrier3_output
      gap: 0.02              # total free play [rad]
      stiffness: 400.0       # spline/shaft stiffness in contact [N m/rad]
      damping: 0.2           # contact damping [N m s]
      load_inertia: 0.002    # output shaft + load [kg m^2]
      load_damping: 0.001    # optional, load bearing drag [N m s] (default 0)
    measurement_delay:       # latency of the speed measurement chain [s]
      seconds: 0.004
    wet_brake:               # wet-to-dry band engagement; key "all" or band1 / band2 / band3
      all: {viscous_time: 0.03, viscous_coefficient: 0.02, viscous_fraction: 0.4,
            asperity_time: 0.08, release_time: 0.01}
    friction_velocity: 0.05  # optional, regularisation speed of friction sign() [rad/s]
    gravity_arm:             # an undeclared arm under gravity behind an output stage on carrier 3
      output_stage: {reduction: 20.0, efficiency: 1.0}     # dvt_model.load YAML schema
      arm: {length: 0.5, mass: 10.0, payload: 2.0, zero_angle: -1.5708}
    mesh_ripple:             # torque ripple on the sun shaft at the sun gear's tooth order
      amplitude: 0.03        # [N m]
      stage: 1               # whose sun's teeth give the order (1..3; default 1)
      phase: 0.0             # optional [rad]
    position_friction:       # a friction bump at one angle of a member (a tight spot)
      carrier3: {amplitude: 0.3, center: 1.0, width: 0.3}   # [N m], [rad], [rad]
    bands:                   # the band brakes as built: per band 1, 2, 3 (each key optional)
      gain: [6.5, 9.5, 7.2]  # static torque per brake-motor ampere [N m/A]
      time_constant: [0.03, 0.015, 0.025]   # first-order engagement [s]

In a preset any number may instead be a distribution, drawn per plant seed
(:mod:`~dvt_driver.plant.hidden.draw`: ``{uniform: [lo, hi], fixed: v}``, ``{log_uniform: [lo,
hi], fixed: v}``, ``{choice: [v1, v2, ...], fixed: v}``): :func:`load_hidden` with ``draw=seed``
draws them, with ``draw=None`` takes each ``fixed`` value (the preset's nominal plant). The
bundled effect presets draw their magnitudes, the gravity arm's reduction and the mesh
ripple's stage (hence its order), so a test compares what the identifier finds with the drawn
truth in ``truth.yaml`` (``hidden``; the draw under ``hidden_draw``), not with a value that
could sit in the identifier's priors. The changing plants (``changes``) are fixed schedules.

A plant that changes while it runs (``changes``, plus the base ``damping_scale``)::

    damping_scale: 1.0       # optional: the transmission's viscous damping D times this (>= 0)
    changes:                 # optional: time-varying effects, applied in order of ``at``
      - at: 30.0             # [s] of plant time (physics time since the plant started)
        ramp: 60.0           # optional [s]: linear from the values in force at ``at`` (0: step)
        coulomb: {carrier3: 0.4}   # sets these members' Coulomb levels [N m] (others kept)
        windage: {sun: 2.0e-6}     # sets these members' quadratic drag [N m s^2]
        damping_scale: 0.8         # sets the scale of D (oil warming: damping falls)
        load: arm-payload          # sets the declared joint load (a step; dvt_model.load
                                   # preset or load YAML path; ``none`` removes it)
        note: "band wear"          # optional text, copied into truth.yaml

A change sets the values it lists (members it does not list keep theirs); with ``ramp`` the
numbers move linearly from the values in force at ``at`` to the new ones over ``ramp``
seconds (a load always steps). :func:`scheduled_values` evaluates a schedule at a time (pure);
:class:`~dvt_driver.plant.core.PlantSim` applies it as its physics time passes, records every
change it applies (``PlantSim.changes_applied``) and writes both into ``truth.yaml`` (``hidden:
changes:`` the schedule; ``changes_applied:`` what happened, with the plant time and, from
``dvt-plant``, the host wall-clock time). ``dvt-plant`` also takes changes at runtime
(``--change-at T:SPEC``, ``--change-file`` + SIGHUP; :mod:`dvt_driver.plant.server`).
Presets: ``wear`` (Coulomb friction on carrier 3 rising), ``oil_warmup`` (damping falling),
``payload_added`` (the arm's payload added; run the plant with ``--load arm``),
``friction_step`` (a clear Coulomb step on both shafts, for tests).

Position-dependent effects (they need the angles the plant integrates, ``theta = (theta_sun,
theta_carrier3)`` [rad] from the plant's start; a member's angle is its linear form times
``theta``):

- ``gravity_arm``: a :class:`dvt_model.load.JointLoad` the plant carries but does not declare
  (the declared one is ``dvt-plant --load``): reflected inertia ``J_arm / reduction^2`` on
  carrier 3 and the gravity torque ``-(Mp/2 + Ma) l g cos(theta_c3 / reduction + zero_angle)
  / reduction`` (efficiency as in :mod:`dvt_model.load`). Effect name ``gravity_load``.
- ``mesh_ripple``: ``T = amplitude * sin(Z * theta_sun + phase)`` on the sun shaft, ``Z`` the
  tooth count of stage ``stage``'s sun in the parameter set (16 in the bundled sets): a torque
  periodic in the sun-shaft angle at the sun gear's tooth order. The plant applies its mean
  over each physics step at the step's speed (exact for a constant speed; no aliasing of the
  640 Hz ripple at 2400 rpm into a 1 kHz step). Effect name ``mesh_ripple``.
- ``position_friction``: ``F = amplitude * exp(-(wrap(phi - center) / width)^2) *
  tanh(v / v_eps)`` against the member's speed ``v``, ``phi`` the member's angle, ``wrap`` into
  ``[-pi, pi)``: a once-per-revolution tight spot (a dented bearing race, an eccentric seal).
  Coulomb and Stribeck depend on the speed only and the windage on ``|v|``; none of the
  identifier's candidates has a friction that depends on where the member stands. Effect name
  ``position_friction``.

Members are the kinematic members of :mod:`dvt_model.kinematics`: ``sun``, ``ring1..3``,
``carrier1..3``, ``planet1..3`` (thesis sign), ``planet1..3_abs``, ``planet1..3_rel``.

Friction on a member acts on that member's speed ``v = a . omega`` (``a`` its linear form in
``omega = (omega_sun, omega_carrier3)``) and contributes the generalised torque ``-a F(v)``
(virtual work). The laws are :mod:`dvt_model.laws`' (``coulomb``, ``stribeck``,
``windage``: the same code the identifier and the model node use). Both friction laws use
``tanh(v / v_eps)`` in place of ``sign(v)``; ``v_eps`` is
``friction_velocity`` raised where needed so that an explicit step of the plant stays stable
(:func:`dvt_driver.plant.physics.friction_velocity_floor`). The Stribeck curve is

    F(v) = (Fc + (Fs - Fc) exp(-|v / vs|^delta)) tanh(v / v_eps)

(break-away ``Fs`` at rest falling to ``Fc`` above ``vs``), which differs from Coulomb by the
hump at low speed.

Any law of the table (:data:`dvt_model.laws.LAWS`) can act on a member through ``laws``:
``{member: [{law: NAME, FIELD: value, ...}, ...]}`` with the law's fields (those with a default
may be left out) within its bounds, the sign smoothed with the member's ``v_eps`` (e.g.
``laws: {carrier3: [{law: stribeck, Fs: 0.2, vs: 1.5}]}``); a law added to the table reaches
the plant this way without a change here. Effect name: the law's name.

``bands`` is no effect the model lacks: it replaces the parameter set's shared band law
(``dvt_model.params.BrakeParams``: one gain from the band geometry and lining, one lag) by each
band's own gain and lag, which the model carries (``band_gain``, ``band_time_constant``) and
the identifier fits in its baseline; a plant without it runs the parameter set's law, the
identifier's prior. Effect name ``bands``.

Presets (``config/*.yaml`` in this package): ``none``, ``coulomb``, ``stribeck``, ``windage``,
``backlash``, ``delay``, ``wet_brake``, ``gravity_arm``, ``mesh_ripple``, ``position_friction``,
``bands`` (drawn per seed), and the changing plants ``wear``, ``oil_warmup``, ``payload_added``,
``friction_step`` (:func:`available_presets`, :func:`load_hidden`).

Modules: :mod:`~dvt_driver.plant.hidden.effects` (the effects as data, the schedule,
``truth.yaml``), :mod:`~dvt_driver.plant.hidden.parse` (presets, YAML, runtime changes),
:mod:`~dvt_driver.plant.hidden.draw` (a preset's distributions drawn from a seed); the
forces the plant computes from them are in :mod:`dvt_driver.plant.physics`. Every public name
is importable from this package.

Errors name the source, the key path and the value, e.g.
``coulomb.yaml: coulomb.sunn: unknown member (expected one of [...])``.
"""

from dvt_driver.plant.hidden.draw import DISTRIBUTIONS, is_distribution, random_draw, resolve
from dvt_driver.plant.hidden.effects import (
    BACKLASH_LOCATIONS,
    DEFAULT_FRICTION_VELOCITY,
    MEMBERS,
    Backlash,
    Bands,
    Change,
    HiddenEffects,
    MeshRipple,
    PositionFriction,
    ScheduledValues,
    StribeckFriction,
    WetBrake,
    scheduled_values,
)
from dvt_driver.plant.hidden.parse import (
    MAX_DAMPING_SCALE,
    available_presets,
    changes_from_spec,
    load_hidden,
    parse_change,
    parse_hidden,
)

__all__ = [
    "BACKLASH_LOCATIONS",
    "DEFAULT_FRICTION_VELOCITY",
    "DISTRIBUTIONS",
    "MAX_DAMPING_SCALE",
    "MEMBERS",
    "Backlash",
    "Bands",
    "Change",
    "HiddenEffects",
    "MeshRipple",
    "PositionFriction",
    "ScheduledValues",
    "StribeckFriction",
    "WetBrake",
    "available_presets",
    "changes_from_spec",
    "is_distribution",
    "load_hidden",
    "parse_change",
    "parse_hidden",
    "random_draw",
    "resolve",
    "scheduled_values",
]
