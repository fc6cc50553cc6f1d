"""Waves in particle models: absorbing boundaries, input histories, monitors,
and the models of 001 they are checked on (the P-wave bar, the Lamb problem).

Citations ("001 eq 4") refer to the documents listed in REFERENCES.md.

* :mod:`jdem.waves.boundaries` the in-step physics: viscous, viscoelastic,
  input and free-field boundaries (001 eq 3–21), driven discs and point loads,
  passed to the engine as ``boundary=(apply_conditions, conditions)``;
* :mod:`jdem.waves.pulses` pulses (001 eq 12, 19), incident waves, prescribed
  velocities and force histories;
* :mod:`jdem.waves.monitors` velocity / position records of groups of discs;
* :mod:`jdem.waves.media` wave parameters and bonded packings;
* :mod:`jdem.waves.bar` the P-wave bar and its reflection measurements;
* :mod:`jdem.waves.calibration` beta by the ratio iteration or by gradient;
* :mod:`jdem.waves.lamb` the Lamb problem.

Every public name is also available here, e.g. ``jdem.waves.bar_model``.
"""
from jdem.waves.pulses import (  # noqa: F401
    Driven,
    History,
    Incident,
    PointLoad,
    at,
    cosine_pulse,
    fix_driven,
    incident_wave,
    lamb_pulse,
    make_driven,
    make_point_load,
    zero_history,
)
from jdem.waves.boundaries import (  # noqa: F401
    Boundary,
    BoundarySet,
    Conditions,
    FreeField,
    SIDES,
    activate,
    apply_conditions,
    boundary_force,
    boundary_particles,
    column_stress,
    exposed_particles,
    free_field_coupling,
    free_field_force,
    make_boundary,
    no_free_field,
    viscoelastic_stiffness,
)
from jdem.waves.monitors import (  # noqa: F401
    Monitors,
    monitor_groups,
    slice_groups,
)
from jdem.waves.media import (  # noqa: F401
    contact_modulus,
    edge_packing,
    lattice,
    random_packing,
    square_density,
    square_packing,
    stable_dt,
    wave_params,
)
from jdem.waves.bar import (  # noqa: F401
    BarModel,
    BarPair,
    INPUTS,
    bar_model,
    bar_pair,
    cut_packing,
    motion_direction,
    peak,
    reflection,
    reflection_against_reference,
    run_bar,
    with_betas,
    with_boundary_monitors,
)
from jdem.waves.calibration import (  # noqa: F401
    Calibration,
    arriving_peak,
    bar_energy,
    calibrate_gradient,
    calibrate_ratio,
    ratio_iteration,
    reflected_energy,
)
from jdem.waves.lamb import (  # noqa: F401
    LAMB_BOUNDARIES,
    LambModel,
    lamb_model,
    run_lamb,
)
