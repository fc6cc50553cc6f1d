"""The half-space Lamb problem of 001 §3.2, Fig 15: a surface point load on a
square lattice with viscous, viscoelastic or fixed far boundaries.

Citations ("001 eq 19") refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.simulate import make_state, run
from jdem.state import Params
from jdem.validate import InputError, require_positive
from jdem.waves.boundaries import (Conditions, activate, apply_conditions, boundary_particles,
                                   make_boundary, viscoelastic_stiffness)
from jdem.waves.media import (contact_modulus, lattice, square_density, square_packing, stable_dt,
                              wave_params)
from jdem.waves.monitors import Monitors, monitor_groups
from jdem.waves.pulses import lamb_pulse, make_point_load


class LambModel(NamedTuple):
    """The half-space Lamb problem of 001 §3.2, Fig 15, ready to run.

    The quarter ... see :func:`lamb_model`.  ``monitors`` holds one group, the
    surface disc ``offset`` [m] from the load; ``n_steps``, ``record_every`` the
    schedule; ``boundary`` the kind ("viscous", "viscoelastic" or "fixed").
    """

    state: object
    params: Params
    config: object
    conditions: Conditions
    monitors: Monitors
    n_steps: int
    record_every: int
    boundary: str



LAMB_BOUNDARIES = ("viscous", "viscoelastic", "fixed")



def lamb_model(size, radius, *, boundary="viscoelastic", c_p=300.0, density=2500.0,
               load=450e3, duration=0.5, offset=10.0, alpha_n=1.0, alpha_s=0.5,
               source_distance=None, t_end=2.0, dt_factor=0.9, record_every=5,
               chunk_steps=500) -> LambModel:
    """The Lamb problem of 001 §3.2 on a square arrangement of equal discs.

    A ``size`` x ``size`` [m] half model (x >= 0 from the symmetry axis, depth
    below the free surface y = 0) of discs of ``radius`` [m]; the load
    F(t) = P0 f(t) (001 eq 19, ``load`` P0 [N], ``duration`` T0 [s]) pushes
    down on the disc at the top left, half of it on the half model (P0 / 2);
    the symmetry axis (left column) is a roller (x velocity fixed).  Bonds with
    nu_b = 0 and fixed rotations make the lattice's long-wave moduli along its
    axes those of an elastic solid with E = rho c_P^2, nu = 0, so c_S = c_P / sqrt 2.
    The right and bottom boundaries are ``"viscous"`` (001 eq 5, beta = 1),
    ``"viscoelastic"`` (001 eq 17 with K from eq 14: E = E_c of
    :func:`contact_modulus` as in 001 §3.1, nu = 0, the distance L
    = ``source_distance`` (default ``size``) and alpha_n, alpha_s) or
    ``"fixed"`` (the extended model).  The monitor is the surface disc
    ``offset`` [m] from the loaded one.
    """
    if boundary not in LAMB_BOUNDARIES:
        raise InputError(f"boundary must be one of {LAMB_BOUNDARIES}, got {boundary!r}")
    size = float(require_positive("size", size))
    r = float(require_positive("radius", radius))
    n = int(round(size / (2.0 * r)))
    if n < 4:
        raise InputError(f"size / (2 radius) must be at least 4, got {size / (2 * r)!r}")
    for name, v in (("load", load), ("duration", duration), ("t_end", t_end)):
        require_positive(name, v)
    pos, rad = square_packing(n, n, r, origin=(0.0, -n * 2.0 * r))
    parts, bonds = lattice(pos, rad, square_density(density), fix_rotation=True)
    params = wave_params(c_p, density, bond_poisson=0.0)
    axis = np.nonzero(pos[:, 0] < 1.5 * r)[0]
    parts = parts._replace(fixed_vel=parts.fixed_vel.at[axis, 0].set(True))
    right = boundary_particles(parts, "right")
    bottom = boundary_particles(parts, "bottom")
    if boundary == "fixed":
        ends = np.concatenate([right.index, bottom.index])
        parts = parts._replace(fixed_vel=parts.fixed_vel.at[ends].set(True))
    state, config = make_state(parts, bonds=bonds)
    dtype = parts.pos.dtype
    params = params._replace(dt=jnp.asarray(stable_dt(state, params, config, dt_factor), dtype))

    top_left = int(np.argmin(np.abs(pos[:, 0] - r) + np.abs(pos[:, 1] + r)))
    t, f = lamb_pulse(duration)
    loads = (make_point_load([top_left], t, 0.5 * load * f, (0.0, -1.0), dtype),)
    bounds = ()
    if boundary != "fixed":
        c_s = c_p / math.sqrt(2.0)
        k_n = k_s = 0.0
        if boundary == "viscoelastic":
            e = contact_modulus(c_p, density)
            dist = size if source_distance is None else source_distance
            k_n = viscoelastic_stiffness(e, 0.0, dist, alpha_n)
            k_s = viscoelastic_stiffness(e, 0.0, dist, alpha_s)
        bounds = tuple(make_boundary(s, parts, density=density, c_p=c_p, c_s=c_s, k_n=k_n, k_s=k_s)
                       for s in (right, bottom))
    cond = Conditions(boundaries=bounds, loads=loads)
    state, cond = activate(state, params, config, cond, release=(False, False))
    monitor = monitor_groups(parts, [[r + offset, -r]])
    dt = float(params.dt)
    n_steps = int(math.ceil(t_end / dt / chunk_steps)) * chunk_steps
    return LambModel(state=state, params=params, config=config, conditions=cond,
                     monitors=Monitors(monitor), n_steps=n_steps, record_every=record_every,
                     boundary=boundary)



def run_lamb(model: LambModel, *, progress=False) -> dict:
    """Run the Lamb model; returns ``time`` (R,) [s] and the monitor's vertical
    displacement ``uy`` (R,) [m] (downward negative)."""
    res = run(model.state, model.params, model.config, model.n_steps,
              record_every=model.record_every, observe=model.monitors, chunk_steps=500,
              progress=progress, desc=f"lamb {model.boundary}",
              boundary=(apply_conditions, model.conditions))
    y0 = float(np.asarray(model.monitors(model.state, model.params, model.config)["pos"])[0, 1])
    return dict(time=res.history["time"], uy=res.history["pos"][:, 0, 1] - y0)
