"""Absorbing (non-reflecting) boundaries for dynamic DEM analyses (001 §2–4).

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
  and the reaction force -F_eq is applied instead (:func:`activate`);
* the calibration factor is found by the ratio iteration of 001 §2.2, Fig 5
  (:func:`ratio_iteration`, :func:`calibrate_ratio`), or by gradient descent on
  the reflected energy through the differentiable rollout
  (:func:`calibrate_gradient`).

Sign conventions: ``Boundary.normal`` is the *outward* unit normal and
``Boundary.tangent`` the normal turned by +90 degrees; v_n = v . n, v_s = v . t.
Incident histories are given in the global frame.

Everything acting during a step is a pure JAX function of the state and of a
``Conditions`` pytree (boundaries, prescribed velocities, point loads): it is
passed to the engine as ``boundary=(apply_conditions, conditions)`` (see
:func:`jdem.integrate.physics_step`) and works under ``jit``, ``vmap`` and
``grad``; the calibration factors, densities, wave speeds and stiffnesses are
ordinary traced leaves.  Host-side builders validate their input and raise
:class:`jdem.validate.InputError` naming the field and the value.

The second half of the module drives the one-dimensional P-wave bar of
001 §2.2 (:func:`bar_model`, :func:`run_bar`) on which the calibrations run.
The reflection of a boundary is measured against an extended reference model
with the identical packing (:func:`bar_pair`,
:func:`reflection_against_reference`), so that what a random packing scatters
by itself cancels.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import integrate, timestep
from jdem.bond import bond_strain_energy, create_bonds
from jdem.kinematics import dot
from jdem.measure import kinetic_energy
from jdem.simulate import make_state, rollout, run
from jdem.specimen import generate, subset
from jdem.state import Params, make_params, make_particles
from jdem.validate import InputError, require_finite, require_positive

Array = jnp.ndarray
SIDES = {"left": (-1.0, 0.0), "right": (1.0, 0.0), "bottom": (0.0, -1.0), "top": (0.0, 1.0)}


# ============================================================================ histories
class History(NamedTuple):
    """A tabulated time history, linearly interpolated (held constant outside).

    time   (K,)    [s], increasing
    value  (K, d)  the quantity (velocity [m/s], displacement [m] or force [N])
    """

    time: Array
    value: Array


def at(history: History, t) -> Array:
    """The history's value (d,) at time ``t`` [s] (jit / grad friendly)."""
    return jax.vmap(lambda col: jnp.interp(t, history.time, col), in_axes=1)(history.value)


def _check_pulse(amplitude, duration, start, samples):
    require_finite("amplitude", amplitude)
    require_positive("duration", duration)
    require_positive("start", start, allow_zero=True)
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 3:
        raise InputError(f"samples must be an integer >= 3, got {samples!r}")


def cosine_pulse(amplitude, duration, *, start=0.0, samples=2001):
    """The harmonic pulse of 001 eq 12 and its integral, as NumPy arrays (K,).

    v(t) = 0.5 M (1 - cos(2 pi (t - t0) / T)) for 0 <= t - t0 <= T, else 0;
    u(t) = 0.5 M ((t - t0) - T / (2 pi) sin(2 pi (t - t0) / T)), 0.5 M T afterwards.
    ``amplitude`` M is the peak velocity [m/s], ``duration`` T [s], ``start`` t0 [s].
    Returns ``(time, velocity, displacement)``.
    """
    _check_pulse(amplitude, duration, start, samples)
    s = np.linspace(0.0, float(duration), int(samples))
    phase = 2.0 * np.pi * s / duration
    vel = 0.5 * amplitude * (1.0 - np.cos(phase))
    disp = 0.5 * amplitude * (s - duration / (2.0 * np.pi) * np.sin(phase))
    return s + float(start), vel, disp


def lamb_pulse(duration, *, start=0.0, samples=2001):
    """The load shape f(t) of 001 eq 19 (K,), peak 1 at t0 + T0 / 2:

    f(t) = 16 [G(t/T0) - 4 G(t/T0 - 1/4) + 6 G(t/T0 - 1/2) - 4 G(t/T0 - 3/4) + G(t/T0 - 1)],
    G(x) = x^3 H(x).  Returns ``(time, f)``; f = 0 outside [t0, t0 + T0].
    """
    _check_pulse(1.0, duration, start, samples)
    s = np.linspace(0.0, float(duration), int(samples))
    x = s / duration
    g = lambda y: np.where(y > 0, y, 0.0) ** 3
    f = 16.0 * (g(x) - 4 * g(x - 0.25) + 6 * g(x - 0.5) - 4 * g(x - 0.75) + g(x - 1.0))
    return s + float(start), f


def _history(time, scalar, direction, dtype) -> History:
    direction = np.asarray(direction, np.float64)
    return History(time=jnp.asarray(time, dtype),
                   value=jnp.asarray(np.outer(scalar, direction), dtype))


def _zero_history(dim, dtype) -> History:
    return History(time=jnp.asarray([0.0, 1.0], dtype), value=jnp.zeros((2, dim), dtype))


# ============================================================================ pytrees
class Incident(NamedTuple):
    """Incident wave at an input boundary (001 eq 6, 18), global frame.

    vel   History (K, d) incident particle velocity v_i [m/s]
    disp  History (K, d) incident displacement u_i [m] (viscoelastic input only)
    """

    vel: History
    disp: History


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


class Driven(NamedTuple):
    """Prescribed velocity history on K discs (the "fixed boundary with velocity
    input" of 001 §2.2).  The driven components must be ``fixed_vel`` in the state
    (:func:`fix_driven`).

    index  (K,)  int32 particle rows
    vel    History (T, d) velocity [m/s], evaluated at mid-step t + dt/2
    mask   (d,)  bool: which components are driven
    """

    index: Array
    vel: History
    mask: Array


class PointLoad(NamedTuple):
    """A force history applied to each of K discs (the Lamb load of 001 eq 19).

    index  (K,)  int32 particle rows
    force  History (T, d) force [N] on each disc
    """

    index: Array
    force: History


class Conditions(NamedTuple):
    """Everything :func:`apply_conditions` adds to a step: tuples (static length)
    of :class:`Boundary`, :class:`Driven` and :class:`PointLoad`."""

    boundaries: tuple = ()
    driven: tuple = ()
    loads: tuple = ()


# ============================================================================ identification
class BoundarySet(NamedTuple):
    """Discs on one straight boundary (host arrays): ``index`` (B,), equivalent
    diameter ``width`` (B,) [m], outward ``normal`` (2,), ``tangent`` (2,), and
    ``position`` of the boundary line along the normal [m]."""

    index: np.ndarray
    width: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    position: float


def _outward(side):
    if isinstance(side, str):
        if side not in SIDES:
            raise InputError(f"side must be one of {tuple(SIDES)} or a normal vector, got {side!r}")
        return np.asarray(SIDES[side])
    n = require_finite("side", side).reshape(-1)
    if n.shape != (2,) or np.linalg.norm(n) == 0:
        raise InputError(f"side must be a non-zero 2D normal vector, got {side!r}")
    return n / np.linalg.norm(n)


def _candidate_rows(particles, among):
    """Indices of the valid particles, restricted to ``among`` if given (non-empty)."""
    rows = np.nonzero(np.asarray(particles.valid))[0]
    if among is not None:
        rows = np.intersect1d(rows, np.asarray(among, np.int64))
    if rows.size == 0:
        raise InputError("among selects no valid particle")
    return rows


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
    rows = _candidate_rows(particles, among)
    n = _outward(side)
    tol = 0.5 * rad[rows].min() if tolerance is None else float(
        require_positive("tolerance", tolerance, allow_zero=True))
    edge = pos[rows] @ n + rad[rows]
    outer = edge.max()
    pick = rows[edge >= outer - tol]
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
    zero = _zero_history(2, dtype)
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


def incident_wave(time, velocity, displacement, direction, dtype=None) -> tuple[History, History]:
    """Incident velocity and displacement histories (K, 2) along the unit vector
    ``direction`` (global frame), e.g. from :func:`cosine_pulse`.  For a P wave
    entering through a boundary the direction is the inward normal; for SV the
    tangent."""
    d = require_finite("direction", direction).reshape(-1)
    if d.shape != (2,) or np.linalg.norm(d) == 0:
        raise InputError(f"direction must be a non-zero 2D vector, got {direction!r}")
    d = d / np.linalg.norm(d)
    dtype = dtype or jnp.zeros(()).dtype
    return _history(time, velocity, d, dtype), _history(time, displacement, d, dtype)


def _indexed_history(index, time, values, direction, *, name, verb, dtype):
    """Checked particle indices (int32) and the history ``values`` (K,) along
    ``direction`` at ``time`` (K,), shared by driven discs and point loads."""
    d = require_finite("direction", direction).reshape(-1)
    require_finite(name, values)
    dtype = dtype or jnp.zeros(()).dtype
    idx = np.asarray(index, np.int64).reshape(-1)
    if idx.size == 0:
        raise InputError(f"index selects no particle to {verb}")
    return jnp.asarray(idx, jnp.int32), _history(time, values, d, dtype)


def make_driven(index, time, velocity, direction, *, mask=None, dtype=None) -> Driven:
    """Prescribed velocity ``velocity`` (K,) [m/s] along ``direction`` at ``time``
    (K,) [s] on the discs ``index``; ``mask`` (2,) bool the driven components
    (default: both)."""
    idx, vel = _indexed_history(index, time, velocity, direction, name="velocity", verb="drive",
                                dtype=dtype)
    m = np.ones(vel.value.shape[-1:], bool) if mask is None else np.asarray(mask, bool)
    return Driven(index=idx, vel=vel, mask=jnp.asarray(m))


def make_point_load(index, time, force, direction, dtype=None) -> PointLoad:
    """Force ``force`` (K,) [N] along ``direction`` at ``time`` (K,) [s] on each
    disc of ``index`` (e.g. ``P0 * lamb_pulse(T0)``, 001 eq 19)."""
    idx, hist = _indexed_history(index, time, force, direction, name="force", verb="load",
                                 dtype=dtype)
    return PointLoad(index=idx, force=hist)


def fix_driven(state, driven: Driven):
    """Mark the driven components of the driven discs as prescribed (``fixed_vel``)."""
    p = state.particles
    fixed = p.fixed_vel.at[driven.index].set(p.fixed_vel[driven.index] | driven.mask[None])
    return state._replace(particles=p._replace(fixed_vel=fixed))


# ============================================================================ forces
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
    force = _unbalanced_force(state, params, config)
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


# ============================================================================ monitors
@dataclasses.dataclass(frozen=True)
class Monitors:
    """Velocity and position records of groups of discs, an ``observe`` function
    for :func:`jdem.run` / :func:`jdem.rollout` (hashable, so compiled runs are
    reused).  Each group is averaged: ``vel`` (K, d) [m/s], ``pos`` (K, d) [m]."""

    groups: tuple

    def _table(self):
        width = max(len(g) for g in self.groups)
        idx = np.zeros((len(self.groups), width), np.int32)
        w = np.zeros((len(self.groups), width))
        for k, g in enumerate(self.groups):
            idx[k, :len(g)] = g
            w[k, :len(g)] = 1.0 / len(g)
        return idx, w

    def __call__(self, state, params, config):
        idx, w = self._table()
        p = state.particles
        w = jnp.asarray(w, p.pos.dtype)[..., None]
        return dict(time=state.time, vel=jnp.sum(w * p.vel[idx], axis=1),
                    pos=jnp.sum(w * p.pos[idx], axis=1))


def monitor_groups(particles, points, *, radius=None) -> tuple:
    """Groups of disc rows near each point (K, 2) [m]: the nearest valid disc, or
    with ``radius`` [m] every valid disc whose centre lies within it (at least
    the nearest)."""
    pos = np.asarray(particles.pos, np.float64)
    rows = np.nonzero(np.asarray(particles.valid))[0]
    pts = require_finite("points", points).reshape(-1, pos.shape[1])
    groups = []
    for q in pts:
        dist = np.linalg.norm(pos[rows] - q, axis=1)
        near = rows[dist <= radius] if radius is not None else np.zeros(0, np.int64)
        if near.size == 0:
            near = rows[[int(np.argmin(dist))]]
        groups.append(tuple(int(k) for k in near))
    return tuple(groups)


def slice_groups(particles, axis, positions, half_width) -> tuple:
    """Groups of the discs whose centre coordinate along ``axis`` lies within
    ``half_width`` [m] of each position (at least the nearest disc)."""
    pos = np.asarray(particles.pos, np.float64)
    rows = np.nonzero(np.asarray(particles.valid))[0]
    groups = []
    for x in np.atleast_1d(positions):
        dist = np.abs(pos[rows, axis] - x)
        near = rows[dist <= half_width]
        if near.size == 0:
            near = rows[[int(np.argmin(dist))]]
        groups.append(tuple(int(k) for k in near))
    return tuple(groups)


# ============================================================================ media
def wave_params(c_p, density, *, bond_poisson=0.0, dt=1.0, dim=2) -> Params:
    """Params for elastic wave problems with linked-bar bonds (002 §1).

    The bond modulus is E_b = rho c_P^2 (001 eq 10, 11 with the whole stiffness
    in the bond): in a square arrangement of equal discs the bond stiffness
    K_n = E_b A_c / L = E_b makes the 1D P-wave speed c_P.  Bonds never break
    (strengths 1e12 Pa), friction and damping are zero (001 §2.2), unbonded
    contacts (rare, in random packings) get k_n = k_s = E_b x 1 m.
    """
    c = float(require_positive("c_p", c_p))
    rho = float(require_positive("density", density))
    e = rho * c * c
    return make_params(dim=dim, dt=dt, kn=e, ks=e, friction=0.0, bond_youngs=e,
                       bond_poisson=bond_poisson, bond_tensile=1e12, bond_cohesion=1e12,
                       bond_tensile_strain=0.0, bond_shear_strain=0.0)


def contact_modulus(c_p, density, alpha_c=0.5):
    """E_c = alpha_c rho c_P^2 [Pa] (001 eq 11, alpha_c = 0.5): the modulus 001
    §3.1 puts into eq 14 in place of the assembly's E (with nu = 0)."""
    return float(alpha_c) * float(require_positive("density", density)) * \
        float(require_positive("c_p", c_p)) ** 2


def square_packing(nx, ny, radius, *, origin=(0.0, 0.0)):
    """Centres (nx ny, 2) and radii of equal discs in a square arrangement, row by
    row from the lower left (Pattern A of 001 Fig 2), lower-left corner at ``origin``."""
    for name, v in (("nx", nx), ("ny", ny)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"{name} must be a positive integer, got {v!r}")
    r = float(require_positive("radius", radius))
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
    pos = np.stack([gx.ravel(), gy.ravel()], axis=1) * 2.0 * r + r + np.asarray(origin, float)
    return pos, np.full(nx * ny, r)


def square_density(density):
    """Disc density [kg/m^3] that gives the macroscopic density ``density`` in a
    square arrangement: m = rho (2r)^2, i.e. rho_disc = 4 rho / pi."""
    return 4.0 * float(require_positive("density", density)) / math.pi


def lattice(pos, rad, disc_density, *, fix_rotation=False, dtype=None):
    """Particles and bonds of an assembly whose touching neighbours are bonded."""
    p = make_particles(pos, rad, density=disc_density, dtype=dtype)
    if fix_rotation:
        p = p._replace(fixed_rot=jnp.ones_like(p.fixed_rot))
    bonds = create_bonds(p, 2, gap_tolerance=1e-6 * float(np.min(rad)))
    return p, bonds


def random_packing(length, height, r_min, r_max, *, density=2500.0, seed=0, fix_rotation=False):
    """A bonded random packing of [0, length] x [0, height] (Pattern B of 001 Fig 2:
    radii uniform in [r_min, r_max]) from :func:`jdem.specimen.generate`, with
    disc density rho / (1 - porosity) so that the macroscopic density is
    ``density``.  Returns ``(particles, bonds, porosity)``."""
    sp = generate("rectangle", (float(length), float(height)), r_min, r_max, seed=seed)
    solid = 1.0 - sp.porosity
    p = sp.particles
    parts = make_particles(np.asarray(p.pos), np.asarray(p.radius), density=density / solid)
    if fix_rotation:
        parts = parts._replace(fixed_rot=jnp.ones_like(parts.fixed_rot))
    return parts, sp.bonds, float(sp.porosity)


def stable_dt(state, params, config, factor=0.5):
    """``factor`` times the critical time step of the bonded assembly [s]."""
    crit = float(timestep.critical_timestep(state, params._replace(dt=jnp.asarray(1.0)), config))
    if not np.isfinite(crit):
        raise InputError("stable_dt: nothing is bonded or touching")
    return factor * crit


# ============================================================================ P-wave bar
class BarModel(NamedTuple):
    """The long bar of 001 Fig 1 (§2.2, §3.1), ready to run.

    state, params, config  the engine inputs (y fixed on every disc)
    conditions   Conditions(boundaries=(left, right), driven=(left drive,), loads=())
    monitors     Monitors: slices at ``monitor_x`` (the input and output boundary
                 discs at the ends)
    monitor_x    (5,) [m] positions P1..P5 along the bar
    length, height  [m];  c_p [m/s], density [kg/m^3] (nominal)
    amplitude, duration  the input pulse (001 eq 12) [m/s], [s]
    n_steps, record_every
    input        "velocity" (left discs driven) or "viscous" (001 eq 6)
    """

    state: object
    params: Params
    config: object
    conditions: Conditions
    monitors: Monitors
    monitor_x: np.ndarray
    length: float
    height: float
    c_p: float
    density: float
    amplitude: float
    duration: float
    n_steps: int
    record_every: int
    input: str


INPUTS = ("velocity", "viscous")


def bar_model(particles, bonds, *, length, height, c_p=1000.0, density=2500.0, amplitude=0.5,
              duration=0.5, input="velocity", beta_left=1.0, beta_right=1.0, k_right=0.0,
              t_end=None, dt_factor=0.5, record_every=1, chunk_steps=2000, dt=None,
              right: BoundarySet | None = None, monitors: tuple | None = None) -> BarModel:
    """The P-wave bar of 001 §2.2 on a given packing of [0, length] x [0, height].

    Every disc's y velocity is fixed (001 Fig 1).  The left boundary carries the
    input: ``input="velocity"`` drives its discs with the pulse of 001 eq 12
    (amplitude [m/s], duration [s]) — the "fixed" left end of 001 §2.2 —, or
    ``"viscous"`` makes it a viscous input boundary (001 eq 6) with beta_left.
    The right boundary is viscous (001 eq 4) with beta_right, viscoelastic when
    ``k_right`` [Pa/m] > 0 (001 eq 17).  Monitors P1..P5 every length/4 (001
    Fig 3) are slices one mean diameter wide; P1 and P5 are the boundary discs.
    ``t_end`` [s] defaults to the time the reflection from the right end takes to
    return to the middle and pass it, 2 length / c_p + duration.  ``dt`` is
    ``dt_factor`` x the critical step; ``n_steps`` is rounded up to whole chunks
    of ``chunk_steps`` so that every run of this size reuses one compiled chunk.
    ``dt`` [s] overrides the step (to run two models on the same clock),
    ``right`` (a :class:`BoundarySet`) the right boundary discs (default
    :func:`boundary_particles` on "right"), ``monitors`` (5 tuples of disc rows)
    the monitor groups P1..P5.
    """
    if input not in INPUTS:
        raise InputError(f"input must be one of {INPUTS}, got {input!r}")
    length = float(require_positive("length", length))
    height = float(require_positive("height", height))
    for name, v in (("amplitude", amplitude), ("duration", duration), ("dt_factor", dt_factor)):
        require_positive(name, v)
    if t_end is not None:
        require_positive("t_end", t_end)
    if chunk_steps % record_every:
        raise InputError(f"record_every = {record_every} must divide chunk_steps = {chunk_steps}")
    dtype = particles.pos.dtype
    params = wave_params(c_p, density)
    parts = particles._replace(fixed_vel=particles.fixed_vel.at[:, 1].set(True))
    state, config = make_state(parts, bonds=bonds)
    step = stable_dt(state, params, config, dt_factor) if dt is None else float(
        require_positive("dt", dt))
    params = params._replace(dt=jnp.asarray(step, dtype))

    left = boundary_particles(parts, "left")
    right = boundary_particles(parts, "right") if right is None else right
    time, vel, disp = cosine_pulse(amplitude, duration)
    inward = np.array([1.0, 0.0])
    c_s = c_p / math.sqrt(2.0)
    if input == "velocity":
        v_in, u_in = incident_wave(time, 0 * vel, 0 * disp, inward, dtype)
        drive = make_driven(left.index, time, vel, inward, mask=(True, False), dtype=dtype)
        state = fix_driven(state, drive)
        beta_left = 0.0
    else:
        v_in, u_in = incident_wave(time, vel, disp, inward, dtype)
        drive = make_driven(left.index, time, 0 * vel, inward, mask=(False, False), dtype=dtype)
    lb = make_boundary(left, parts, density=density, c_p=c_p, c_s=c_s, beta_p=beta_left,
                       beta_s=beta_left, incident_vel=v_in, incident_disp=u_in)
    rb = make_boundary(right, parts, density=density, c_p=c_p, c_s=c_s, beta_p=beta_right,
                       beta_s=beta_right, k_n=k_right, k_s=k_right)
    cond = Conditions(boundaries=(lb, rb), driven=(drive,))
    # nothing is loaded yet (F_eq = 0); the y fixity and the driven x stay
    state, cond = activate(state, params, config, cond, release=(False, False))

    x = np.linspace(0.0, length, 5)
    r_mean = float(np.mean(np.asarray(parts.radius)[np.asarray(parts.valid)]))
    groups = list(slice_groups(parts, 0, x, r_mean))
    groups[0] = tuple(int(k) for k in left.index)
    groups[-1] = tuple(int(k) for k in right.index)
    if monitors is not None:
        groups = [tuple(int(k) for k in g) for g in monitors]
    if t_end is None:
        t_end = 2.0 * length / c_p + duration
    dt = float(params.dt)
    per_chunk = chunk_steps
    n_steps = int(math.ceil(t_end / dt / per_chunk)) * per_chunk
    return BarModel(state=state, params=params, config=config, conditions=cond,
                    monitors=Monitors(tuple(groups)), monitor_x=x, length=length, height=height,
                    c_p=float(c_p), density=float(density), amplitude=float(amplitude),
                    duration=float(duration), n_steps=n_steps, record_every=record_every,
                    input=input)


def with_betas(model: BarModel, *, beta_left=None, beta_right=None) -> Conditions:
    """The model's conditions with new calibration factors (beta_2P = beta_2S)."""
    left, right = model.conditions.boundaries
    f = lambda v: jnp.asarray(v, left.beta_p.dtype)
    if beta_left is not None:
        left = left._replace(beta_p=f(beta_left), beta_s=f(beta_left))
    if beta_right is not None:
        right = right._replace(beta_p=f(beta_right), beta_s=f(beta_right))
    return model.conditions._replace(boundaries=(left, right))


def run_bar(model: BarModel, conditions: Conditions | None = None, *, n_steps=None,
            progress=False) -> dict:
    """Run the bar; returns the monitor history: ``time`` (R,) [s], ``vel`` and
    ``disp`` (R, 5, 2) at P1..P5 (displacement from the start) and
    ``state`` (the final state)."""
    cond = model.conditions if conditions is None else conditions
    n = model.n_steps if n_steps is None else int(n_steps)
    res = run(model.state, model.params, model.config, n, record_every=model.record_every,
              observe=model.monitors, chunk_steps=2000, progress=progress, desc="bar",
              boundary=(apply_conditions, cond))
    h = res.history
    pos0 = np.asarray(model.monitors(model.state, model.params, model.config)["pos"])
    return dict(time=h["time"], vel=h["vel"], disp=h["pos"] - pos0[None], state=res.state)


def peak(history: dict, monitor: int, direction=(1.0, 0.0)) -> float:
    """Largest velocity of monitor ``monitor`` along ``direction`` over the record [m/s]."""
    return float(np.max(history["vel"][:, monitor] @ np.asarray(direction, float)))


def reflection(history: dict, model: BarModel, monitor: int = 2) -> dict:
    """Incident and reflected amplitude at a monitor inside the bar (default P3).

    The incident peak ``incident`` is the largest x velocity; the reflected
    amplitude ``reflected`` the largest |x velocity| after the incident pulse
    has passed (peak time + 0.6 T) and before the wave reflected at the right end
    can come back from the left end (peak time + 2 length / c - 0.6 T), with
    the wave speed c measured from the peak times at P2 and P3.  ``ratio`` =
    reflected / incident.
    """
    t = history["time"]
    v = history["vel"][:, :, 0]
    x = model.monitor_x
    first = lambda k: t[int(np.argmax(np.where(t < x[k] / model.c_p + 2.0 * model.duration,
                                               v[:, k], -np.inf)))]
    t2, t3 = first(1), first(2)
    speed = (x[2] - x[1]) / (t3 - t2) if t3 > t2 else model.c_p
    tp = first(monitor)
    lo = tp + 0.6 * model.duration
    hi = tp + 2.0 * model.length / speed - 0.6 * model.duration   # back from the left end
    hi = min(hi, t[-1])
    win = (t >= lo) & (t <= hi)
    inc = float(np.max(v[:, monitor][t <= lo]))
    ref = float(np.max(np.abs(v[win, monitor]))) if np.any(win) else float("nan")
    return dict(incident=inc, reflected=ref, ratio=ref / inc, speed=float(speed),
                window=(float(lo), float(hi)))


# ============================================================================ reflection vs reference
def exposed_particles(particles, side="right", *, among=None) -> BoundarySet:
    """The discs of a ragged (cut) boundary facing ``side``: those whose centre
    sees out along the outward normal, i.e. no other disc of ``among`` (default
    all valid) lies further out with its centre within its own radius of that
    ray.  Returns a :class:`BoundarySet` (D = 2 r, ``position`` the outermost
    edge).  2D only; O(N^2) on the host."""
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    rows = _candidate_rows(particles, among)
    n = _outward(side)
    t = np.array([-n[1], n[0]])
    d = pos[rows][None, :, :] - pos[rows][:, None, :]         # (k, m, 2): m relative to k
    ahead = (d @ n > 0) & (np.abs(d @ t) < rad[rows][None, :])
    pick = rows[~ahead.any(axis=1)]
    pick = pick[np.argsort(pos[pick] @ t)]
    return BoundarySet(index=pick, width=2.0 * rad[pick], normal=n, tangent=t,
                       position=float(np.max(pos[pick] @ n + rad[pick])))


def cut_packing(particles, bonds, x_max):
    """The discs of a packing whose centre lies at x <= ``x_max`` [m] and the
    bonds between them (rows renumbered, order kept; :func:`jdem.specimen.subset`).
    Returns ``(particles, bonds, rows)`` with ``rows`` (M,) the kept rows of the
    input, so that ``rows[k]`` is the original row of new disc k."""
    pos = np.asarray(particles.pos, np.float64)
    keep = np.asarray(particles.valid) & (pos[:, 0] <= float(x_max))
    if not keep.any():
        raise InputError(f"x_max = {x_max!r} keeps no particle")
    return subset(particles, bonds, keep)


class BarPair(NamedTuple):
    """A truncated bar and its extended reference (:func:`bar_pair`).

    truncated, reference  BarModels on one clock, with the same monitor discs
    clean_until  (5,) [s] at each monitor P1..P5, the earliest time anything
                 from the reference's far end could arrive there
    record       [s] the part of the record that counts, 2 length / c_p + T
    """

    truncated: BarModel
    reference: BarModel
    clean_until: np.ndarray
    record: float


def bar_pair(particles, bonds, *, length, height, monitor=2, c_max=None, **kwargs) -> BarPair:
    """A truncated bar and its extended reference, cut from one long packing.

    ``particles``, ``bonds``: a packing of [0, L_ext] x [0, height] [m]; the
    truncated model (:func:`bar_model`, same keywords) keeps the discs with
    centre x <= ``length`` [m] (:func:`cut_packing`), its right boundary the
    discs exposed on the cut (:func:`exposed_particles`; on a random packing
    the cut is ragged); the reference is the whole packing with the same left
    input, the same time step and record and the same monitor discs (P5: the
    truncated model's right boundary discs, inside the reference).  In
    [0, length] the two are the same disc for disc, so the packing's own
    scattering is the same in both.  The reference's far end (viscous,
    beta = 1) must be so far away that nothing from there reaches monitor
    ``monitor`` within the record 2 length / c_p + T: with the fastest speed
    ``c_max`` (default 1.2 c_p) it arrives at x_m after (2 L_ext - x_m) / c_max;
    InputError otherwise.  Returns a :class:`BarPair`.
    """
    kw = dict(kwargs)
    for name in ("dt", "right", "monitors", "t_end"):
        if name in kw:
            raise InputError(f"bar_pair sets {name} itself")
    parts, bnd, rows = cut_packing(particles, bonds, length)
    right = exposed_particles(parts, "right")
    params = wave_params(kw.get("c_p", 1000.0), kw.get("density", 2500.0))
    dts = []
    for p_, b_ in ((parts, bnd), (particles, bonds)):
        st, cf = make_state(p_._replace(fixed_vel=p_.fixed_vel.at[:, 1].set(True)), bonds=b_)
        dts.append(stable_dt(st, params, cf, kw.get("dt_factor", 0.5)))
    dt = min(dts)                                 # one clock for both models
    trunc = bar_model(parts, bnd, length=length, height=height, right=right, dt=dt, **kw)
    t_end = (trunc.n_steps - 0.5) * dt            # the same whole chunks for the reference
    monitors = tuple(tuple(int(rows[k]) for k in g) for g in trunc.monitors.groups)
    ref = bar_model(particles, bonds, length=length, height=height, dt=dt, t_end=t_end,
                    monitors=monitors, **kw)
    if ref.n_steps != trunc.n_steps:
        raise RuntimeError("bar_pair: the two records differ in length")
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    l_ext = float(np.max((pos[:, 0] + rad)[np.asarray(particles.valid)]))
    c = 1.2 * trunc.c_p if c_max is None else float(require_positive("c_max", c_max))
    clean = (2.0 * l_ext - trunc.monitor_x) / c
    record = 2.0 * trunc.length / trunc.c_p + trunc.duration
    if clean[monitor] < record:
        raise InputError(f"the packing is too short for a reference: its far end at {l_ext:.1f} m "
                         f"can reach monitor {monitor} after {clean[monitor]:.3f} s, within the "
                         f"record {record:.3f} s (need L_ext >= "
                         f"{0.5 * (c * record + trunc.monitor_x[monitor]):.1f} m)")
    return BarPair(truncated=trunc, reference=ref, clean_until=clean, record=record)


def reflection_against_reference(truncated: dict, reference: dict, *, monitor=2, incident=None,
                                 t_max=None, component=0) -> dict:
    """Reflected amplitude at a monitor, measured against an extended reference.

    ``truncated`` and ``reference`` are monitor histories (:func:`run_bar`) of
    the model with the absorbing boundary and of the extended model with the
    identical packing where they overlap (:func:`bar_pair`): ``time`` (R,) [s]
    on the same clock and ``vel`` (R, M, 2) [m/s] at the same monitor discs.
    Whatever the packing scatters by itself is in both and cancels; the
    difference is what the truncation sends back.  Only times t <= ``t_max``
    [s] count (default: the whole record; for a :class:`BarPair` pass
    ``pair.record``).  ``incident`` [m/s] is the peak incident amplitude
    (default: the largest ``component`` velocity of the reference at the
    monitor).  Returns ``reflected`` = max |v_truncated - v_reference| [m/s],
    ``incident``, ``ratio`` = reflected / incident, ``time`` [s] of the largest
    difference and ``difference`` (R,) [m/s] over the whole record.
    """
    ta, tb = np.asarray(truncated["time"]), np.asarray(reference["time"])
    if ta.shape != tb.shape or not np.allclose(ta, tb, rtol=1e-9, atol=0.0):
        raise InputError("truncated and reference records must share their time axis")
    va = np.asarray(truncated["vel"])[:, monitor, component]
    vb = np.asarray(reference["vel"])[:, monitor, component]
    diff = va - vb
    win = np.ones(ta.shape, bool) if t_max is None else ta <= float(t_max)
    if not np.any(win):
        raise InputError(f"t_max = {t_max!r} leaves no record")
    inc = float(np.max(vb[win])) if incident is None else float(
        require_positive("incident", incident))
    k = int(np.argmax(np.where(win, np.abs(diff), -np.inf)))
    ref = float(np.abs(diff[k]))
    return dict(incident=inc, reflected=ref, ratio=ref / inc, time=float(ta[k]), difference=diff)


# ============================================================================ calibration
class Calibration(NamedTuple):
    """Result of a calibration: ``beta``; ``history`` a list of dicts, one per
    iteration (``beta``, ``m_out``, ``ratio`` for the ratio iteration; ``beta``,
    ``loss``, ``grad`` for gradient descent); ``converged``."""

    beta: float
    history: list
    converged: bool


def ratio_iteration(peak_of: Callable[[float], float], m_input, *, beta0=1.0, tol=1e-3,
                    max_iter=15, mode="absorbing") -> Calibration:
    """The ratio iteration of 001 §2.2, Fig 5.

    ``peak_of(beta)`` runs the short test with calibration factor beta and returns
    the peak velocity M_out at the boundary; ``m_input`` is the input peak M_in.
    Each iteration runs the test; it stops when |M_out / M_in - 1| < ``tol``,
    else beta is multiplied by M_out / M_in (``mode="absorbing"``: an
    under-absorbing boundary moves too fast, so beta grows) or by M_in / M_out
    (``mode="input"``, 001 §2.3.3: an input boundary moves too slowly when beta
    is too small).  At most ``max_iter`` runs.
    """
    if mode not in ("absorbing", "input"):
        raise InputError(f"mode must be 'absorbing' or 'input', got {mode!r}")
    beta = float(require_positive("beta0", beta0))
    require_positive("m_input", m_input)
    require_positive("tol", tol)
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise InputError(f"max_iter must be a positive integer, got {max_iter!r}")
    history = []
    for k in range(1, int(max_iter) + 1):
        m_out = float(peak_of(beta))
        if not (np.isfinite(m_out) and m_out > 0):
            raise RuntimeError(f"ratio_iteration: the test returned M_out = {m_out} at beta = {beta}")
        ratio = m_out / float(m_input)
        history.append(dict(iteration=k, beta=beta, m_out=m_out, ratio=ratio))
        if abs(ratio - 1.0) < tol:
            return Calibration(beta=beta, history=history, converged=True)
        beta = beta * (ratio if mode == "absorbing" else 1.0 / ratio)
    return Calibration(beta=beta, history=history, converged=False)


def calibrate_ratio(model: BarModel, *, boundary="right", beta0=1.0, tol=1e-3, max_iter=15,
                    beta_other=None) -> Calibration:
    """Ratio iteration (001 Fig 5) on the bar ``model``, running it each time.

    ``boundary="right"``: the absorbing boundary; M_out is the peak x velocity of
    the right boundary discs (P5), M_in the input pulse amplitude.
    ``boundary="left"``: the viscous input boundary of a model built with
    ``input="viscous"``; M_out is the peak x velocity of the left boundary discs
    (P1), and beta is scaled by M_in / M_out.  ``beta_other`` fixes the factor of
    the other boundary (default: as built).
    """
    if boundary not in ("left", "right"):
        raise InputError(f"boundary must be 'left' or 'right', got {boundary!r}")
    if boundary == "left" and model.input != "viscous":
        raise InputError("calibrating the left (input) boundary needs a model built with "
                         f"input='viscous', got input={model.input!r}")

    def peak_of(beta):
        if boundary == "right":
            cond = with_betas(model, beta_right=beta, beta_left=beta_other)
            return peak(run_bar(model, cond), 4)
        cond = with_betas(model, beta_left=beta, beta_right=beta_other)
        return peak(run_bar(model, cond), 0)

    return ratio_iteration(peak_of, model.amplitude, beta0=beta0, tol=tol, max_iter=max_iter,
                           mode="absorbing" if boundary == "right" else "input")


def bar_energy(state, params) -> Array:
    """Kinetic plus bond strain energy of the assembly [J per m thickness]."""
    return kinetic_energy(state) + bond_strain_energy(state.bonds, state.particles, params, 2)


def _energy_observe(state, params, config):
    return dict(energy=bar_energy(state, params))


@functools.lru_cache(maxsize=8)
def _reflected_energy_fn(config, n_records, record_every, i_full):
    """Jitted value-and-grad of the reflected energy fraction w.r.t. log beta."""

    def loss(log_beta, state, params, cond):
        right = cond.boundaries[1]
        beta = jnp.exp(log_beta)
        right = right._replace(beta_p=beta, beta_s=beta)
        cond = cond._replace(boundaries=(cond.boundaries[0], right))
        _, hist = rollout(state, params, config, n_records, record_every, _energy_observe,
                          boundary=(apply_conditions, cond))
        e = hist["energy"]
        return e[-1] / e[i_full]

    return jax.jit(jax.value_and_grad(loss))


def reflected_energy(model: BarModel, beta, *, t_end=None, record_every=50):
    """Reflected energy fraction E(t_end) / E(t_full) of the bar with the right
    factor ``beta`` and its derivative d/d(log beta), through the differentiable
    rollout.  E is the kinetic plus bond energy in the bar; t_full = 1.2 T (the
    pulse is all in), t_end (default (length + c T) / c + 0.5 length / c) when
    the incident pulse has left through the right end and the reflection is on
    its way back.  Returns ``(fraction, d fraction / d log beta)``."""
    dt = float(model.params.dt)
    if t_end is None:
        t_end = 1.5 * model.length / model.c_p + model.duration
    n_records = int(math.ceil(t_end / dt / record_every))
    i_full = int(math.ceil(1.2 * model.duration / dt / record_every))
    fn = _reflected_energy_fn(model.config, n_records, record_every, i_full)
    value, grad = fn(jnp.log(jnp.asarray(beta, model.params.dt.dtype)), model.state,
                     model.params, model.conditions)
    return float(value), float(grad)


def calibrate_gradient(model: BarModel, *, beta0=1.0, steps=15, learning_rate=1.0,
                       t_end=None, record_every=50, tol=1e-3) -> Calibration:
    """Calibrate the right boundary's beta by gradient descent on the reflected
    energy fraction (:func:`reflected_energy`), differentiating through the
    rollout: ``optax.sgd`` on log beta.  Near the optimum the fraction is about
    R^2 with R = (1 - x) / (1 + x) ~ -ln(x) / 2 (x = beta / beta_opt), i.e.
    (ln x)^2 / 4, whose curvature 1/2 makes ``learning_rate`` = 1 halve the
    error each step.  Stops after ``steps`` evaluations or when the step in
    log beta falls below ``tol``.  Returns the beta with the smallest loss seen
    and the history (beta, loss, grad)."""
    import optax

    require_positive("beta0", beta0)
    require_positive("learning_rate", learning_rate)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise InputError(f"steps must be a positive integer, got {steps!r}")
    opt = optax.sgd(learning_rate)
    log_beta = jnp.log(jnp.asarray(beta0, model.params.dt.dtype))
    opt_state = opt.init(log_beta)
    history = []
    converged = False
    for k in range(int(steps)):
        value, grad = reflected_energy(model, float(jnp.exp(log_beta)), t_end=t_end,
                                       record_every=record_every)
        history.append(dict(iteration=k + 1, beta=float(jnp.exp(log_beta)), loss=value, grad=grad))
        updates, opt_state = opt.update(jnp.asarray(grad, log_beta.dtype), opt_state)
        log_beta = optax.apply_updates(log_beta, updates)
        if abs(float(updates)) < tol:
            converged = True
            break
    best = min(history, key=lambda h: h["loss"])
    return Calibration(beta=best["beta"], history=history, converged=converged)


# ============================================================================ Lamb problem
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
