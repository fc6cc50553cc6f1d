"""Absorbing (non-reflecting) boundaries for dynamic DEM analyses (001 §2–4):
the physics that acts during a step.

Citations ("001 eq 4") refer to the documents listed in REFERENCES.md.

A truncated model must let outgoing waves leave; 001 turns the continuum
viscous, viscoelastic and free-field boundary conditions into forces on the
discs of a straight model boundary (2D, unit thickness, SI units):

* **viscous boundary** (001 eq 4, 5): a normal and a tangential dashpot on every
  boundary disc, F_n = -beta_2P D rho c_P v_n, F_s = -beta_2S D rho c_S v_s,
  with D the disc's equivalent diameter (001 eq 2) and beta calibration factors
  (1 for equal discs in a square arrangement, 001 eq 3);
* **input boundary** (001 eq 6, wave-field decomposition): the same dashpots plus
  2 beta D rho c v_i for an incident velocity history v_i;
* **viscoelastic boundary** (001 eq 17, 18): springs K D u in parallel with the
  dashpots, K_n, K_s from 001 eq 14 (:func:`viscoelastic_stiffness`), and
  K D u_i for an input boundary;
* **free-field boundary** (001 eq 20, 21): for waves entering vertically from the
  base, the lateral boundary discs are tied by dashpots to the discs of a
  free-field column at the same height, and the column's stress is applied
  to them;
* every boundary starts from the static state (001 §2.1): the fixity is removed
  and the reaction force -F_eq is applied instead (:func:`activate`).

Sign conventions: ``Boundary.normal`` is the *outward* unit normal and
``Boundary.tangent`` the normal turned by +90 degrees; v_n = v . n, v_s = v . t.
Incident histories are given in the global frame.

Everything acting during a step is a pure JAX function of the state and of a
:class:`Conditions` pytree (boundaries, prescribed velocities, point loads): it
is passed to the engine as ``boundary=(apply_conditions, conditions)`` (see
:func:`jdem.integrate.physics_step`) and works under ``jit``, ``vmap`` and
``grad``; the calibration factors, densities, wave speeds and stiffnesses are
ordinary traced leaves.  Host-side builders validate their input and raise
:class:`jdem.validate.InputError` naming the field and the value.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import integrate
from jdem.kinematics import dot
from jdem.specimen.loads import FACES, face_particles, outward_normal, valid_rows
from jdem.state import Params
from jdem.validate import InputError, require_finite, require_positive
from jdem.waves.pulses import Incident, zero_history, at

Array = jnp.ndarray


SIDES = FACES[2]



class FreeField(NamedTuple):
    """Coupling of a lateral boundary to a free-field column (001 eq 20, 21).

    For B boundary discs: ``on`` (B,) bool says which have a partner;
    ``column`` (B,) int32 the partner disc of the column at the same height;
    ``bond_below`` / ``bond_above`` (B,) int32 the column's bond rows (in
    ``state.bonds``) below and above the partner, ``has_below`` / ``has_above``
    (B,) bool whether they exist; ``width`` (B,) [m] the column width D_ff;
    ``poisson`` () nu, which gives the column's horizontal normal stress
    sigma_xx = nu / (1 - nu) sigma_yy (laterally confined); ``stress0`` (B, 2)
    the column's (tau_xy, sigma_yy) [Pa] when the boundary was switched on (the
    static part, already balanced by the reaction force).
    """

    on: Array
    column: Array
    bond_below: Array
    bond_above: Array
    has_below: Array
    has_above: Array
    width: Array
    poisson: Array
    stress0: Array



class Boundary(NamedTuple):
    """Dashpots (and springs) on the B discs of one straight boundary.

    index        (B,)   int32 particle rows
    width        (B,)   equivalent diameter D [m] (001 eq 2: the disc diameter)
    normal       (d,)   outward unit normal
    tangent      (d,)   unit tangent (normal turned +90 degrees)
    density      ()     rho of the medium [kg/m^3]
    c_p, c_s     ()     P and S wave speeds [m/s]
    beta_p, beta_s ()   calibration factors beta_2P, beta_2S (001 eq 4)
    k_n, k_s     ()     viscoelastic spring stiffness [Pa/m] (001 eq 14; 0: viscous)
    static_force (B, d) reaction force replacing the removed fixity, -F_eq [N] (001 eq 5)
    ref_pos      (B, d) positions when the boundary was switched on [m]
    incident     :class:`Incident` (zero histories on a non-input boundary)
    free_field   :class:`FreeField` (all ``on = False`` without a free field)
    """

    index: Array
    width: Array
    normal: Array
    tangent: Array
    density: Array
    c_p: Array
    c_s: Array
    beta_p: Array
    beta_s: Array
    k_n: Array
    k_s: Array
    static_force: Array
    ref_pos: Array
    incident: Incident
    free_field: FreeField



class Conditions(NamedTuple):
    """Everything :func:`apply_conditions` adds to a step: tuples (static length)
    of :class:`Boundary`, :class:`Driven` and :class:`PointLoad`."""

    boundaries: tuple = ()
    driven: tuple = ()
    loads: tuple = ()



class BoundarySet(NamedTuple):
    """Discs on one straight boundary (host arrays): ``index`` (B,), equivalent
    diameter ``width`` (B,) [m], outward ``normal`` (2,), ``tangent`` (2,), and
    ``position`` of the boundary line along the normal [m]."""

    index: np.ndarray
    width: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    position: float



def boundary_particles(particles, side, *, tolerance=None, among=None) -> BoundarySet:
    """The discs on the straight boundary of the assembly facing ``side``.

    ``side`` is "left", "right", "bottom", "top" or an outward normal (2,).  A
    disc is on the boundary when its outer edge n . x + r lies within
    ``tolerance`` [m] (default half the smallest radius) of the outermost edge;
    ``among`` (optional index array) restricts the search, e.g. to the main model.
    Returns a :class:`BoundarySet`; D = 2 r (001 eq 2).  2D only.
    """
    pos = np.asarray(particles.pos, np.float64)
    if pos.shape[1] != 2:
        raise InputError(f"boundary_particles works on 2D discs, got dimension {pos.shape[1]}")
    rad = np.asarray(particles.radius, np.float64)
    pick, n, outer = face_particles(particles, side, tolerance=tolerance, among=among)
    t = np.array([-n[1], n[0]])
    pick = pick[np.argsort(pos[pick] @ t)]
    return BoundarySet(index=pick, width=2.0 * rad[pick], normal=n, tangent=t,
                       position=float(outer))



def viscoelastic_stiffness(youngs, poisson, distance, alpha):
    """001 eq 14: K = alpha E / (2 L (1 + nu)) [Pa/m] (= alpha G / L).

    ``youngs`` E [Pa], ``poisson`` nu, ``distance`` L from the wave source to the
    boundary [m], ``alpha`` the boundary coefficient alpha_n or alpha_s.
    """
    e = float(require_positive("youngs", youngs))
    nu = float(require_finite("poisson", poisson))
    if not -1.0 < nu < 0.5:
        raise InputError(f"poisson must lie in (-1, 0.5), got {nu!r}")
    length = float(require_positive("distance", distance))
    a = float(require_positive("alpha", alpha, allow_zero=True))
    return a * e / (2.0 * length * (1.0 + nu))



def make_boundary(bset: BoundarySet, particles, *, density, c_p, c_s, beta_p=1.0, beta_s=1.0,
                  k_n=0.0, k_s=0.0, incident_vel=None, incident_disp=None,
                  free_field: FreeField | None = None) -> Boundary:
    """A :class:`Boundary` on the discs of ``bset``.

    density [kg/m^3], c_p, c_s [m/s] of the medium; beta_p, beta_s calibration
    factors (001 eq 4); k_n, k_s spring stiffness [Pa/m] (001 eq 14, 0 for a
    viscous boundary); incident_vel / incident_disp: a :class:`History` of the
    incident velocity / displacement (input boundary, 001 eq 6, 18).  The
    reaction force and reference positions start at zero / the current
    positions; :func:`activate` sets them from a static state.
    """
    require_positive("density", density)
    require_positive("c_p", c_p)
    require_positive("c_s", c_s)
    for name, v in (("beta_p", beta_p), ("beta_s", beta_s), ("k_n", k_n), ("k_s", k_s)):
        require_positive(name, v, allow_zero=True)
    dtype = particles.pos.dtype
    f = lambda v: jnp.asarray(v, dtype)
    idx = jnp.asarray(bset.index, jnp.int32)
    b = idx.shape[0]
    if b == 0:
        raise InputError("the boundary set holds no particle")
    zero = zero_history(2, dtype)
    incident = Incident(vel=incident_vel if incident_vel is not None else zero,
                        disp=incident_disp if incident_disp is not None else zero)
    ff = free_field if free_field is not None else no_free_field(b, dtype)
    return Boundary(index=idx, width=f(bset.width), normal=f(bset.normal), tangent=f(bset.tangent),
                    density=f(density), c_p=f(c_p), c_s=f(c_s), beta_p=f(beta_p),
                    beta_s=f(beta_s), k_n=f(k_n), k_s=f(k_s),
                    static_force=jnp.zeros((b, 2), dtype), ref_pos=particles.pos[idx],
                    incident=incident, free_field=ff)



def no_free_field(b: int, dtype) -> FreeField:
    """A free-field record for B discs with no partner."""
    zi = jnp.zeros((b,), jnp.int32)
    zb = jnp.zeros((b,), bool)
    return FreeField(on=zb, column=zi, bond_below=zi, bond_above=zi, has_below=zb, has_above=zb,
                     width=jnp.ones((b,), dtype), poisson=jnp.zeros((), dtype),
                     stress0=jnp.zeros((b, 2), dtype))



def free_field_coupling(particles, bonds, bset: BoundarySet, column, *, poisson=0.0) -> FreeField:
    """Tie the discs of the lateral boundary ``bset`` to a free-field column (001 eq 21).

    ``column`` (K,) are the rows of the column's discs from the bottom up: a
    one-disc-wide stack, bonded to its neighbours only, carrying the same base
    input as the main model (its base disc is an input boundary of its own).
    With fixed rotations such a stack moves exactly like a laterally uniform
    square arrangement under vertically incident waves.  Each boundary disc is
    paired with the column disc nearest in height.  ``poisson`` nu gives the
    column's sigma_xx = nu / (1 - nu) sigma_yy (0 for the seed's nu = 0).
    """
    pos = np.asarray(particles.pos, np.float64)
    col = np.asarray(column, np.int64).reshape(-1)
    if col.size < 2:
        raise InputError(f"column must hold at least 2 discs, got {col.size}")
    if np.any(np.diff(pos[col, 1]) <= 0):
        raise InputError("column must list its discs from the bottom up")
    nu = float(require_finite("poisson", poisson))
    if not -1.0 < nu < 0.5:
        raise InputError(f"poisson must lie in (-1, 0.5), got {nu!r}")
    bi, bj = np.asarray(bonds.i), np.asarray(bonds.j)
    ok = np.asarray(bonds.valid)

    def bond_row(a, b):
        lo, hi = min(a, b), max(a, b)
        rows = np.nonzero(ok & (bi == lo) & (bj == hi))[0]
        return (int(rows[0]), True) if rows.size else (0, False)

    partner = np.array([col[np.argmin(np.abs(pos[col, 1] - pos[k, 1]))] for k in bset.index])
    k_of = {int(c): k for k, c in enumerate(col)}
    below, above = [], []
    for c in partner:
        k = k_of[int(c)]
        below.append(bond_row(col[k - 1], c) if k > 0 else (0, False))
        above.append(bond_row(c, col[k + 1]) if k + 1 < col.size else (0, False))
    for name, pairs in (("below", below), ("above", above)):
        for (row, found), c in zip(pairs, partner):
            if found and not pos[bi[row], 1] < pos[bj[row], 1]:   # column_stress needs i below j
                raise InputError(f"the column bond {name} disc {c} does not run from the lower "
                                 f"disc to the upper one; number the column from the bottom up")
    rad = np.asarray(particles.radius, np.float64)
    dtype = particles.pos.dtype
    b = len(bset.index)
    return FreeField(on=jnp.ones((b,), bool), column=jnp.asarray(partner, jnp.int32),
                     bond_below=jnp.asarray([r for r, _ in below], jnp.int32),
                     bond_above=jnp.asarray([r for r, _ in above], jnp.int32),
                     has_below=jnp.asarray([f for _, f in below]),
                     has_above=jnp.asarray([f for _, f in above]),
                     width=jnp.asarray(2.0 * rad[partner], dtype), poisson=jnp.asarray(nu, dtype),
                     stress0=jnp.zeros((b, 2), dtype))



def column_stress(bonds, particles, ff: FreeField) -> Array:
    """(tau_xy, sigma_yy) [Pa] (B, 2) of the free-field column at each partner disc:
    the bond forces on the lower disc of the bonds below and above it, divided by
    the column width, averaged (tension positive, continuum convention).  The
    column's bonds must run from the lower disc ``i`` to the upper disc ``j``.
    """
    def traction(row):
        i, j = bonds.i[row], bonds.j[row]
        branch = particles.pos[j] - particles.pos[i]
        n = branch / jnp.linalg.norm(branch, axis=-1, keepdims=True)
        # force on the lower disc (jdem.bond: -F_n n + F_s, F_n > 0 in compression)
        return -bonds.normal_force[row][:, None] * n + bonds.shear_force[row]

    below = jnp.where(ff.has_below[:, None], traction(ff.bond_below), 0.0)
    above = jnp.where(ff.has_above[:, None], traction(ff.bond_above), 0.0)
    count = ff.has_below.astype(below.dtype) + ff.has_above.astype(below.dtype)
    mean = (below + above) / jnp.maximum(count, 1.0)[:, None]
    return mean / ff.width[:, None]     # (tau_xy, sigma_yy): traction on a horizontal plane



def free_field_force(b: Boundary, state) -> tuple[Array, Array]:
    """Velocity of the free field v_ff (B, 2) and the force D sigma_ff . n (B, 2)
    the free field exerts on each boundary disc (001 eq 20, 21)."""
    ff = b.free_field
    p = state.particles
    v_ff = jnp.where(ff.on[:, None], p.vel[ff.column], 0.0)
    tau, syy = jnp.moveaxis(column_stress(state.bonds, p, ff) - ff.stress0, -1, 0)
    sxx = ff.poisson / (1.0 - ff.poisson) * syy
    nx, ny = b.normal[0], b.normal[1]
    traction = jnp.stack([sxx * nx + tau * ny, tau * nx + syy * ny], axis=-1)  # sigma . n
    f_ff = jnp.where(ff.on[:, None], b.width[:, None] * traction, 0.0)
    return v_ff, f_ff



def boundary_force(b: Boundary, state) -> Array:
    """Force (B, 2) [N] on the discs of one boundary at the start of a step.

    F = -F_eq - [beta_2P D rho c_P (v - v_ff - 2 v_i) . n + K_n D (u - u_i) . n] n
              - [beta_2S D rho c_S (v - v_ff - 2 v_i) . t + K_s D (u - u_i) . t] t + F_ff

    which is 001 eq 5 (non-input), eq 6 (input, v_i != 0), eq 17, 18
    (viscoelastic, K != 0) and eq 21 (free field).  v is the disc's velocity
    (the leapfrog half-step value), u its displacement since switch-on.
    """
    p = state.particles
    t = state.time
    v = p.vel[b.index]
    u = p.pos[b.index] - b.ref_pos
    v_i = at(b.incident.vel, t)
    u_i = at(b.incident.disp, t)
    v_ff, f_ff = free_field_force(b, state)
    dv = v - v_ff - 2.0 * v_i[None]              # 001 eq 6: wave-field decomposition
    du = u - u_i[None]
    rho_d = b.density * b.width
    f_n = b.beta_p * rho_d * b.c_p * dot(dv, b.normal) + b.k_n * b.width * dot(du, b.normal)
    f_s = b.beta_s * rho_d * b.c_s * dot(dv, b.tangent) + b.k_s * b.width * dot(du, b.tangent)
    return b.static_force - f_n[:, None] * b.normal - f_s[:, None] * b.tangent + f_ff



def apply_conditions(state, params: Params, cond: Conditions):
    """The engine hook (see :func:`jdem.integrate.physics_step`): set the driven
    velocities at mid-step, and return the boundary and load forces (N, 2) [N]."""
    p = state.particles
    vel = p.vel
    for drv in cond.driven:
        target = at(drv.vel, state.time + 0.5 * params.dt)
        vel = vel.at[drv.index].set(jnp.where(drv.mask[None], target[None], vel[drv.index]))
    state = state._replace(particles=p._replace(vel=vel))
    force = jnp.zeros_like(p.pos)
    for b in cond.boundaries:
        force = force.at[b.index].add(boundary_force(b, state))
    for load in cond.loads:
        force = force.at[load.index].add(at(load.force, state.time)[None])
    return state, force



@functools.partial(jax.jit, static_argnames=("config",))
def _unbalanced_force(state, params, config):
    return integrate.forces(state, params, config)[1]



def activate(state, params: Params, config, cond: Conditions, *, release=(True, True)):
    """Switch the boundaries on from a static state (001 §2.1).

    1. the unbalanced force F_eq of every boundary disc is measured with the
       boundary forces off (contacts, bonds, gravity, applied loads);
    2. the fixity of the boundary discs is removed (components where ``release``
       (2,) is True);
    3. the reaction force -F_eq is stored in ``static_force`` so the initial
       stress state stays in equilibrium, the current positions become the
       reference for the viscoelastic springs and the free-field columns'
       current stress the static stress.

    Returns ``(state, conditions)``.
    """
    force = _unbalanced_force(state, params, config.without_search_grid())
    free = jnp.asarray(np.asarray(release, bool))
    p = state.particles
    fixed = p.fixed_vel
    boundaries = []
    for b in cond.boundaries:
        fixed = fixed.at[b.index].set(fixed[b.index] & ~free[None])
        stress0 = column_stress(state.bonds, p, b.free_field)
        ff = b.free_field._replace(stress0=jnp.where(b.free_field.on[:, None], stress0, 0.0))
        boundaries.append(b._replace(static_force=-force[b.index], ref_pos=p.pos[b.index],
                                     free_field=ff))
    state = state._replace(particles=p._replace(fixed_vel=fixed))
    return state, cond._replace(boundaries=tuple(boundaries))



def exposed_particles(particles, side="right", *, among=None) -> BoundarySet:
    """The discs of a ragged (cut) boundary facing ``side``: those whose centre
    sees out along the outward normal, i.e. no other disc of ``among`` (default
    all valid) lies further out with its centre within its own radius of that
    ray.  Returns a :class:`BoundarySet` (D = 2 r, ``position`` the outermost
    edge).  2D only; O(N^2) on the host."""
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    rows = valid_rows(particles, among)
    n = outward_normal(side, 2)
    t = np.array([-n[1], n[0]])
    d = pos[rows][None, :, :] - pos[rows][:, None, :]         # (k, m, 2): m relative to k
    ahead = (d @ n > 0) & (np.abs(d @ t) < rad[rows][None, :])
    pick = rows[~ahead.any(axis=1)]
    pick = pick[np.argsort(pos[pick] @ t)]
    return BoundarySet(index=pick, width=2.0 * rad[pick], normal=n, tangent=t,
                       position=float(np.max(pos[pick] @ n + rad[pick])))
