"""The computing cycle of the block method (000 §2.3.2, eq 2-9..2-17).

Citations ("000 eq 2-15") refer to the documents listed in REFERENCES.md.

One step:

1. refresh the pair list if some centroid moved half the skin (:mod:`jdem.blocks.detect`);
2. contact geometry of every listed pair, relative velocity at each contact
   point (000 eq 2-9, 2-10), the joint law (:func:`jdem.blocks.joint.coulomb_point`,
   000 eq 2-11, or the continuously yielding joint where the joint has one,
   :func:`jdem.blocks.joint.yielding_point`) plus contact dashpots (000 eq 2-12
   in rate form: a fraction ``contact_damping`` of the critical c = 2 sqrt(m* k),
   the shear one off while the point slips, as the book says), forces and
   moments summed on the blocks (000 eq 2-13, 2-14) with gravity and applied loads;
3. damping of the unbalanced force and moment (000 §3.2, the particles' laws of
   :mod:`jdem.damping`);
4. velocities v += F / m dt, spin w += M / I dt (000 eq 2-15), except for
   ``fixed`` blocks, whose motion is prescribed;
5. positions and angles (000 eq 2-16, 2-17).

Same discipline as the particles: ``BlockState`` evolves, ``BlockParams`` are
the traced floats (differentiable: stiffnesses, friction, strengths, damping),
``jdem.state.Config`` is static (the search grid).  Per listed pair the list
keeps its history in ``contacts.shear`` (C, 12), six numbers for each of its two
contact points, in columns [2 k, 2 k + 1] for quantity k:

0. the shear force [N];
1. whether the point is intact (1.0 / 0.0);
2. to 5. the continuously yielding joint's plastic shear displacement u_p [m],
   stress ratio at the last reversal, sign of the last shear increment, and
   accumulated dilation [m] (:func:`jdem.blocks.joint.yielding_point`; zero
   for the other joints).

They carry over rebuilds with the pair, like the disc contacts' shear springs.
"""
from __future__ import annotations

import functools
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import damping, neighbors
from jdem.blocks import detect, joint
from jdem.blocks.geometry import Blocks, signed_area, world_vertices
from jdem.kinematics import cross_r_f, cross_w_r, segment_add
from jdem.simulate import SimulationDiverged, scan_first
from jdem.state import Config, Contacts
from jdem.timestep import damped_limit
from jdem.validate import InputError

# the history of a pair, in this order, one column per contact point (module docstring)
HISTORY_FIELDS = ("shear", "intact", "plastic", "ratio", "sign", "dilation")
HISTORY = len(HISTORY_FIELDS) * detect.POINTS_PER_PAIR


def history_field(history, name):
    """The (C, 2) columns of ``name`` (one of :data:`HISTORY_FIELDS`) in a pair
    list's history ``contacts.shear`` (C, 12)."""
    k = HISTORY_FIELDS.index(name) * detect.POINTS_PER_PAIR
    return history[:, k:k + detect.POINTS_PER_PAIR]


class BlockParams(NamedTuple):
    """Traced parameters of a block system.

    The joint properties form a table over the blocks' materials: the contact
    between a block of material a and one of material b uses entry [a, b]
    (symmetric, (M, M); M = 1 for one kind of joint).  So a joint set, a fault or
    the rock between two joints can each have their own.

    dt               time step [s]
    kn, ks           (M, M) normal and shear stiffness per contact point [N/m]
                     (000 eq 2-1, 2-2)
    friction         (M, M) mu = tan(phi) of the joints [-]
    cohesion         (M, M) shear strength of an intact point at zero normal force [N]
    tension          (M, M) tensile strength of an intact point [N]
    kn_face, ks_face (M, M) normal and shear stiffness of a face contact per unit
                     area [Pa/m] (000 §3.4.1, fig 3-13: edge–edge contacts have
                     stiffness in stress per displacement): where > 0, a pair
                     touching at both ends of its clipped edge of length L
                     (an edge–edge contact) has points of k L / 2 each (000 eq
                     3-36, 3-37); a corner–edge contact keeps ``kn``, ``ks``.  0:
                     every point uses ``kn``, ``ks``
    jrc, jcs         (M, M) Barton's joint roughness coefficient [-] and joint wall
                     compressive strength [Pa] (000 eq 3-43): where jrc > 0 the
                     friction angle of a point is atan(friction) + JRC log10(JCS /
                     sigma_n), sigma_n its normal force over its share of the
                     contact length (half the clipped face, unit thickness)
    cy_friction0     (M, M) tan(phi_0) of a continuously yielding joint (000 §3.4.1
                     item 5): where > 0 the joint follows
                     :func:`jdem.blocks.joint.yielding_point`, its friction angle
                     falling from phi_0 to atan(friction) with the plastic slip;
                     no cohesion, tension or ``jrc`` there
    cy_roughness     (M, M) its roughness R [m]: the plastic slip over which the
                     friction angle falls (half-way at u_p = R / (phi_0 - phi))
    corner_radius    radius of the arcs that round every block corner [m] (000 eq
                     3-34, 3-35, fig 3-12; :func:`jdem.blocks.detect.pair_geometry`);
                     0: sharp corners
    contact_damping  ratio of critical damping of the normal and shear dashpots [-]
    local_damping    alpha of 000 eq 3-19 [-], 0 <= alpha < 1
    viscous_damping  mass-proportional damping c [1/s] (000 eq 3-9)
    gravity          (2,) [m/s^2]
    """

    dt: jnp.ndarray
    kn: jnp.ndarray
    ks: jnp.ndarray
    friction: jnp.ndarray
    cohesion: jnp.ndarray
    tension: jnp.ndarray
    jrc: jnp.ndarray
    jcs: jnp.ndarray
    kn_face: jnp.ndarray
    ks_face: jnp.ndarray
    cy_friction0: jnp.ndarray
    cy_roughness: jnp.ndarray
    corner_radius: jnp.ndarray
    contact_damping: jnp.ndarray
    local_damping: jnp.ndarray
    viscous_damping: jnp.ndarray
    gravity: jnp.ndarray


JOINT_TABLE = ("kn", "ks", "friction", "cohesion", "tension", "jrc", "jcs", "kn_face", "ks_face",
               "cy_friction0", "cy_roughness")


def make_params(*, kn, ks=None, friction=0.5, cohesion=0.0, tension=0.0, jrc=0.0, jcs=1e8,
                kn_face=0.0, ks_face=None, cy_friction0=0.0, cy_roughness=0.0,
                corner_radius=0.0, contact_damping=0.0,
                local_damping=0.0, viscous_damping=0.0, gravity=(0.0, -9.81), dt=None,
                dtype=None) -> BlockParams:
    """Block parameters with checks.

    The joint properties (``kn``, ``ks``, ``friction``, ``cohesion``,
    ``tension``, ``jrc``, ``jcs``, ``kn_face``, ``ks_face``, ``cy_friction0``,
    ``cy_roughness``) are numbers (one
    kind of joint) or symmetric (M, M) tables over the block materials
    (:class:`BlockParams`).  ``ks`` defaults to kn / (2 (1 + 0.25)) (000 eq 3-33
    with nu = 0.25), ``ks_face`` likewise to kn_face / 2.5; ``dt`` to NaN (set
    it with :func:`recommended_timestep` before running).
    """
    ks = np.asarray(kn, dtype=np.float64) / 2.5 if ks is None else ks
    ks_face = np.asarray(kn_face, dtype=np.float64) / 2.5 if ks_face is None else ks_face
    table = dict(kn=kn, ks=ks, friction=friction, cohesion=cohesion, tension=tension, jrc=jrc,
                 jcs=jcs, kn_face=kn_face, ks_face=ks_face, cy_friction0=cy_friction0,
                 cy_roughness=cy_roughness)
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in table.items()}
    # the table size comes from kn if it is a table, else from the first table given
    m = next((a.shape[0] for a in arrays.values() if a.ndim == 2), 1)
    for name, a in arrays.items():
        if a.ndim == 0:
            a = np.full((m, m), float(a))
        if a.shape != (m, m):
            raise InputError(f"block parameter {name} must be a number or an ({m}, {m}) "
                             f"table over the materials, got shape {a.shape}")
        if not np.allclose(a, a.T, rtol=0, atol=0):
            raise InputError(f"block parameter {name} must be a symmetric table, got {a.tolist()}")
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise InputError(f"block parameter {name} must be finite and >= 0, got {a.tolist()}")
        arrays[name] = a
    if np.any(arrays["jcs"] <= 0):
        raise InputError(f"block parameter jcs must be > 0, got {arrays['jcs'].tolist()}")
    if np.any(arrays["kn"] <= 0):
        raise InputError(f"block parameter kn must be > 0, got {arrays['kn'].tolist()}")
    yielding = arrays["cy_friction0"] > 0
    if np.any(yielding & (arrays["cy_friction0"] <= arrays["friction"])):
        raise InputError(f"block parameter cy_friction0 = {arrays['cy_friction0'].tolist()} "
                         f"must exceed friction = {arrays['friction'].tolist()} where it is > 0 "
                         f"(the initial friction angle of a continuously yielding joint)")
    for name in ("cohesion", "tension", "jrc"):
        if np.any(yielding & (arrays[name] > 0)):
            raise InputError(f"block parameter {name} = {arrays[name].tolist()} must be 0 where "
                             f"the joint is continuously yielding (cy_friction0 > 0): that law "
                             f"has no {name}")
    scalars = dict(corner_radius=corner_radius, contact_damping=contact_damping,
                   local_damping=local_damping, viscous_damping=viscous_damping)
    for name, v in scalars.items():
        v = float(v)
        if not np.isfinite(v) or v < 0:
            raise InputError(f"block parameter {name} must be finite and >= 0, got {v!r}")
    if not float(local_damping) < 1.0:
        raise InputError(f"block parameter local_damping must be < 1, got {local_damping!r}")
    g = np.asarray(gravity, dtype=np.float64)
    if g.shape != (2,) or not np.all(np.isfinite(g)):
        raise InputError(f"gravity must be a finite (2,) vector, got {gravity!r}")
    f = jnp.zeros(()).dtype if dtype is None else dtype
    a = lambda x: jnp.asarray(x, f)   # noqa: E731
    return BlockParams(dt=a(np.nan if dt is None else dt), gravity=a(g),
                       **{k: a(v) for k, v in arrays.items()},
                       **{k: a(v) for k, v in scalars.items()})


class BlockState(NamedTuple):
    """blocks: :class:`jdem.blocks.geometry.Blocks`; contacts: the pair list
    (history (C, 4) in ``contacts.shear``, see the module docstring); step: int32."""

    blocks: Blocks
    contacts: Contacts
    step: jnp.ndarray


def make_state(blocks: Blocks, *, skin=None, capacity=None):
    """State and static config of a block system (host): the search grid covers
    the blocks with a margin and the pair list is allocated and built.

    skin  listing distance between bounding circles [m] (default a tenth of the
          smallest bounding radius)
    Returns ``(state, config)``.
    """
    circles = detect.bounding_circles(blocks)
    rad = np.asarray(blocks.radius)[np.asarray(blocks.valid)]
    skin = 0.1 * float(rad.min()) if skin is None else float(skin)
    origin, shape, cell = neighbors.grid_for(circles, skin=skin)
    config = Config(dim=2, skin=skin, cell_size=cell, grid_origin=origin, grid_shape=shape,
                    max_per_cell=8)
    # allocate sizes the list for the pairs it finds (at least ``cap`` rows); the
    # empty list it starts from gives the history its (C, 4) shape
    cap = max(int(capacity or 0), 4 * int(rad.size))
    empty = neighbors.empty(circles, cap)
    empty = empty._replace(shear=jnp.zeros((cap, HISTORY), blocks.pos.dtype))
    contacts, config = neighbors.allocate(circles, config, old=empty, min_capacity=cap)
    return BlockState(blocks=blocks, contacts=contacts, step=jnp.zeros((), jnp.int32)), config


class ContactForces(NamedTuple):
    """Per listed pair and point: ``normal`` (C, 2), ``point`` (C, 2, 2) [m],
    ``fn``, ``fs`` (C, 2) [N] on block j (on i: minus), ``active``, ``sliding``,
    ``intact`` (C, 2) bool, ``overlap`` (C, 2) [m]."""

    normal: jnp.ndarray
    point: jnp.ndarray
    fn: jnp.ndarray
    fs: jnp.ndarray
    active: jnp.ndarray
    sliding: jnp.ndarray
    intact: jnp.ndarray
    overlap: jnp.ndarray


@functools.partial(jax.jit, static_argnames=("sharp_corners", "coulomb_only"))
def contact_forces(state: BlockState, params: BlockParams, *, sharp_corners=False,
                   coulomb_only=False):
    """Joint forces of the listed pairs and their sums on the blocks.

    Returns ``(contacts, force (B, 2) [N], moment (B,) [N m], ContactForces)``,
    ``contacts`` with the updated history.  Gravity and loads are not included.
    ``sharp_corners=True`` (static) skips the rounding of the corners, which then
    must be 0 (:func:`run` sets it after checking: the rounding path costs ~15 %
    of a step even at radius 0, which a traced radius cannot skip).
    ``coulomb_only=True`` (static) likewise skips the continuously yielding law,
    which then must be unused (``cy_friction0`` all 0; :func:`run` checks).
    Jitted: called on its own (a plot, a test), op by op it compiled some 150
    small programs; inside a step it is inlined.
    """
    b, c = state.blocks, state.contacts
    g = detect.pair_geometry(b, c.i, c.j, 0.0 if sharp_corners else params.corner_radius)
    shear_old, intact_old, plastic_old, ratio_old, sign_old, dilation_old = (
        history_field(c.shear, name) for name in HISTORY_FIELDS)
    intact_old = intact_old > 0.5
    ma, mb = b.material[c.i], b.material[c.j]
    kn, ks, mu, coh, ten, jrc, jcs, kn_face, ks_face, mu0, rough_r = (
        getattr(params, name)[ma, mb][:, None] for name in JOINT_TABLE)
    # a continuously yielding point touches while its overlap plus its dilation
    # is positive: the dilation has pushed the faces apart by that much
    dilation_old = jnp.where(mu0 > 0, dilation_old, 0.0)
    active = c.valid[:, None] & g.exists & ((g.separation < dilation_old) | intact_old)
    n = g.normal[:, None, :]                               # (C, 1, 2)
    t = jnp.stack([-n[..., 1], n[..., 0]], axis=-1)
    ri = g.point - b.pos[c.i][:, None, :]
    rj = g.point - b.pos[c.j][:, None, :]
    vi = b.vel[c.i][:, None, :] + cross_w_r(b.angvel[c.i][:, None], ri)
    vj = b.vel[c.j][:, None, :] + cross_w_r(b.angvel[c.j][:, None], rj)
    v_rel = vj - vi                                        # 000 eq 2-9 as rates
    vn = jnp.sum(v_rel * n, axis=-1)                       # 000 eq 2-10
    vt = jnp.sum(v_rel * t, axis=-1)
    overlap = -g.separation
    # an edge–edge contact (both ends of the clipped edge touching) on a joint with
    # a face stiffness: each point carries half the contact length (000 fig 3-13,
    # eq 3-36, 3-37), so a sliver of an edge (e.g. two corners that meet) carries
    # next to nothing; a corner–edge contact keeps its point stiffness
    half = 0.5 * g.length[:, None]
    edge_edge = jnp.all(active, axis=1, keepdims=True)
    kn = jnp.where((kn_face > 0) & edge_edge, kn_face * half, kn)
    ks = jnp.where((ks_face > 0) & edge_edge, ks_face * half, ks)
    # Barton's rough joint (000 eq 3-43) where jrc > 0: the friction angle rises as
    # the point's normal stress falls; the stress from the elastic normal force
    share = jnp.maximum(0.5 * g.length, 1e-6 * (b.radius[c.i] + b.radius[c.j]))[:, None]
    sigma_n = jnp.maximum(kn * overlap, 0.0) / share
    rough = joint.barton_friction(sigma_n, jnp.arctan(mu), jrc, jcs)
    mu = jnp.where(jrc > 0, rough, mu)
    d_shear = vt * params.dt
    fn, fs, intact, sliding = joint.coulomb_point(
        overlap, d_shear, shear_old, intact_old & active, kn, ks, mu, coh, ten)
    plastic, ratio, sign, dilation = plastic_old, ratio_old, sign_old, dilation_old
    if not coulomb_only:
        # the continuously yielding joint: the dilation adds to the overlap
        # (000 §3.4.1 item 5, sigma_n += k_n |du_s| tan i); a point out of touch
        # forgets its dilation, as it forgets its shear force
        yielding = (mu0 > 0) & active
        fn_cy = kn * jnp.maximum(overlap + dilation_old, 0.0)
        fs_cy, plastic_cy, ratio_cy, sign_cy, d_dil, slip_cy = joint.yielding_point(
            fn_cy, d_shear, shear_old, plastic_old, ratio_old, sign_old, ks, mu, mu0, rough_r)
        fn = jnp.where(yielding, fn_cy, fn)
        fs = jnp.where(yielding, fs_cy, fs)
        intact = intact & ~yielding
        sliding = jnp.where(yielding, slip_cy, sliding)
        plastic = jnp.where(yielding, plastic_cy, plastic_old)
        ratio = jnp.where(yielding, ratio_cy, ratio_old)
        sign = jnp.where(yielding, sign_cy, sign_old)
        dilation = jnp.where(yielding, dilation_old + d_dil, 0.0)
    # dashpots (000 eq 2-12 as a fraction of critical); reduced mass, a fixed
    # block counting as infinitely heavy
    mi = jnp.where(b.fixed[c.i], jnp.inf, b.mass[c.i])
    mj = jnp.where(b.fixed[c.j], jnp.inf, b.mass[c.j])
    m_red = jnp.where(jnp.isinf(mi), mj, jnp.where(jnp.isinf(mj), mi, mi * mj / (mi + mj)))
    m_red = jnp.where(jnp.isinf(m_red), 0.0, m_red)[:, None]
    zeta = params.contact_damping
    dn = -2.0 * zeta * jnp.sqrt(m_red * kn) * vn
    ds = jnp.where(sliding, 0.0, -2.0 * zeta * jnp.sqrt(m_red * ks) * vt)
    fn_total = jnp.where(intact, fn + dn, jnp.maximum(fn + dn, 0.0))
    fn_total = jnp.where(active, fn_total, 0.0)
    fs_total = jnp.where(active, fs + ds, 0.0)
    fs = jnp.where(active, fs, 0.0)
    intact = intact & active
    force_j = fn_total[..., None] * n + fs_total[..., None] * t     # (C, 2, 2)
    nb = b.pos.shape[0]
    pair_force = jnp.sum(force_j, axis=1)                               # (C, 2) on j
    force = segment_add(pair_force, c.j, nb) - segment_add(pair_force, c.i, nb)
    moment = segment_add(jnp.sum(cross_r_f(rj, force_j), axis=1), c.j, nb) - \
        segment_add(jnp.sum(cross_r_f(ri, force_j), axis=1), c.i, nb)
    fields = dict(shear=fs, intact=intact.astype(fs.dtype), plastic=plastic, ratio=ratio,
                  sign=sign, dilation=dilation)
    history = jnp.concatenate([fields[name] for name in HISTORY_FIELDS], axis=1)
    contacts = c._replace(shear=jnp.where(c.valid[:, None], history, 0.0))
    info = ContactForces(normal=g.normal, point=g.point, fn=fn_total, fs=fs_total,
                         active=active, sliding=sliding & active, intact=intact,
                         overlap=overlap)
    return contacts, force, moment, info


def step(state: BlockState, params: BlockParams, config: Config, sharp_corners=False,
         coulomb_only=False) -> BlockState:
    """One step of the cycle (module docstring); ``sharp_corners`` and
    ``coulomb_only`` as in :func:`contact_forces`."""
    b = state.blocks
    contacts = neighbors.update(state.contacts, detect.bounding_circles(b), config)
    state = state._replace(contacts=contacts)
    contacts, force, moment, _ = contact_forces(state, params, sharp_corners=sharp_corners,
                                                coulomb_only=coulomb_only)
    force = force + b.mass[:, None] * params.gravity + b.ext_force
    moment = moment + b.ext_torque
    force = damping.viscous_damping(force, b.vel, b.mass, params.viscous_damping)
    moment = damping.viscous_damping(moment, b.angvel, b.inertia, params.viscous_damping)
    force = damping.local_damping(force, b.vel, params.local_damping)
    moment = damping.local_damping(moment, b.angvel, params.local_damping)
    free = b.valid & ~b.fixed
    vel = jnp.where(free[:, None], b.vel + force / b.mass[:, None] * params.dt, b.vel)
    angvel = jnp.where(free, b.angvel + moment / b.inertia * params.dt, b.angvel)
    blocks = b._replace(vel=vel, angvel=angvel, pos=b.pos + vel * params.dt,
                        angle=b.angle + angvel * params.dt)
    return BlockState(blocks=blocks, contacts=contacts, step=state.step + 1)


def glue_joints(state: BlockState, params: BlockParams, config: Config,
                tolerance=0.0, where=None) -> BlockState:
    """Mark every contact point that exists now with a gap below ``tolerance``
    [m] as intact: the joints between these blocks get ``cohesion`` and
    ``tension`` (:mod:`jdem.blocks.joint`).

    where  optional ``where(points (C, 2, 2), normals (C, 2)) -> (C, 2) bool``
           (NumPy) choosing the points to glue, e.g. the rock bridges of a
           non-persistent joint set (:func:`jdem.blocks.generate.bridge_mask`)
    """
    c = neighbors.build(state.contacts, detect.bounding_circles(state.blocks), config)
    g = detect.pair_geometry(state.blocks, c.i, c.j, params.corner_radius)
    glued = c.valid[:, None] & g.exists & (g.separation <= tolerance)
    if where is not None:
        glued = glued & jnp.asarray(where(np.asarray(g.point), np.asarray(g.normal)))
    k = HISTORY_FIELDS.index("intact") * detect.POINTS_PER_PAIR
    hist = c.shear.at[:, k:k + detect.POINTS_PER_PAIR].set(glued.astype(c.shear.dtype))
    return state._replace(contacts=c._replace(shear=hist))


def critical_timestep(blocks: Blocks, params: BlockParams, *, points=None):
    """000 eq 3-24 for every free block, dt < 2 sqrt(m / k), with the dashpots
    counted as for the particles (:func:`jdem.timestep.damped_limit`).

    The stiffness of a block is bounded by its contact points, each pushing with
    k_n + k_s, doubled for neighbours moving against it (Gershgorin, as in
    :mod:`jdem.timestep`); its rotation by the same springs at the bounding
    radius.  ``points``: the contact points per block (default 2 per vertex,
    an upper bound for blocks in a packing).  Returns a scalar [s].
    """
    b = blocks
    z = 2.0 * jnp.sum(b.vert_valid, axis=1) if points is None else points
    # stiffest joint of each block; a face contact's point has k L / 2 <= k R
    # (no edge is longer than the bounding diameter 2 R)
    kn = jnp.maximum(jnp.max(params.kn[b.material], axis=1),
                     jnp.max(params.kn_face[b.material], axis=1) * b.radius)
    k = kn + jnp.maximum(jnp.max(params.ks[b.material], axis=1),
                         jnp.max(params.ks_face[b.material], axis=1) * b.radius)
    c = 2.0 * params.contact_damping * jnp.sqrt(b.mass * kn)
    w2_tr = 2.0 * z * k / b.mass
    g_tr = 2.0 * z * c / b.mass + params.viscous_damping
    w2_rot = 2.0 * z * k * b.radius ** 2 / b.inertia
    g_rot = 2.0 * z * c * b.radius ** 2 / b.inertia + params.viscous_damping
    dt = jnp.minimum(damped_limit(w2_tr, g_tr), damped_limit(w2_rot, g_rot))
    return jnp.min(jnp.where(b.valid & ~b.fixed, dt, jnp.inf))


def recommended_timestep(blocks: Blocks, params: BlockParams, safety=0.5) -> float:
    """``safety`` times :func:`critical_timestep` (host float).  Also checks that
    the corners' arcs fit the blocks: ``corner_radius`` below half the inradius
    2 A / P of every block (else a rounded core would turn inside out)."""
    r = float(params.corner_radius)
    if r > 0:
        keep = np.asarray(blocks.valid)
        w = np.asarray(world_vertices(blocks))[keep]
        vv = np.asarray(blocks.vert_valid)[keep]
        inradius = []
        for verts, ok in zip(w, vv):
            v = verts[ok]
            perimeter = np.sum(np.linalg.norm(np.roll(v, -1, axis=0) - v, axis=1))
            inradius.append(2.0 * abs(signed_area(v)) / perimeter)
        if r >= 0.5 * min(inradius):
            raise InputError(f"block parameter corner_radius = {r!r} m does not fit the "
                             f"smallest block (half its inradius 2 A / P is "
                             f"{0.5 * min(inradius):.3g} m)")
    return float(safety * critical_timestep(blocks, params))


@functools.partial(jax.jit, static_argnames=("config", "n_records", "record_every", "observe",
                                             "sharp_corners", "coulomb_only"))
def rollout(state: BlockState, params: BlockParams, config: Config, n_records: int,
            record_every: int, observe=None, sharp_corners=False, coulomb_only=False,
            n_run=None):
    """``n_records`` x ``record_every`` steps as a pure function (jit, vmap, grad).

    observe        ``observe(state, params) -> dict`` recorded after each block of
                   steps (default: block positions, angles, velocities)
    sharp_corners  skip the corner rounding (:func:`contact_forces`); only when
                   ``params.corner_radius`` is 0 (:func:`run` checks and sets it)
    coulomb_only   skip the continuously yielding law; only when
                   ``params.cy_friction0`` is all 0 (:func:`run` checks and sets it)
    n_run          run only the first ``n_run`` records (traced int; the others
                   are zeros), so that :func:`run`'s last, shorter chunk reuses
                   the program of its full ones (:func:`jdem.simulate.scan_first`)
    Returns ``(state, history)`` with each record stacked on a leading axis.
    """
    observe = observe or default_observe

    def chunk(s, _):
        s = jax.lax.fori_loop(0, record_every,
                              lambda _, x: step(x, params, config, sharp_corners,
                                                coulomb_only), s)
        return s, observe(s, params)

    return scan_first(jax.checkpoint(chunk), state, jnp.arange(n_records), n_run)


def default_observe(state: BlockState, params: BlockParams) -> dict:
    """Positions (B, 2), angles (B,), velocities (B, 2), spins (B,) and the step."""
    b = state.blocks
    return dict(pos=b.pos, angle=b.angle, vel=b.vel, angvel=b.angvel, step=state.step)


def run(state: BlockState, params: BlockParams, config: Config, n_steps: int, *,
        record_every: int = 100, observe=None, progress=True):
    """Host loop over :func:`rollout` chunks: checks the time step first, grows
    the pair list and re-runs a chunk when it overflowed, shows progress.  When
    the state turns non-finite, or a block moves half the skin in one step (it
    could pass through another before the pair list sees them), it raises
    :class:`jdem.simulate.SimulationDiverged` carrying the last good state (the
    start of the chunk) and the history so far.

    Returns ``(state, history as NumPy arrays)``.
    """
    if int(record_every) < 1 or int(n_steps) < 1:
        raise InputError(f"n_steps and record_every must be >= 1, got {n_steps!r}, "
                         f"{record_every!r}")
    n_mat = int(params.kn.shape[0])
    used = int(np.max(np.where(np.asarray(state.blocks.valid), np.asarray(state.blocks.material),
                               0)))
    if used >= n_mat:
        raise InputError(f"block material index {used} is out of range: the joint tables of "
                         f"params have {n_mat} material(s)")
    dt, crit = float(params.dt), float(critical_timestep(state.blocks, params))
    if not np.isfinite(dt) or dt <= 0 or dt > crit:
        raise InputError(f"params.dt = {dt!r} must be in (0, {crit:.4g}] s, the critical "
                         f"step of these blocks (recommended_timestep gives a safe one)")
    sharp = not bool(np.any(np.asarray(params.corner_radius) > 0))
    coulomb_only = not bool(np.any(np.asarray(params.cy_friction0) > 0))

    def chunk(n, k, records):
        nonlocal state, config
        new, hist = rollout(state, params, config, n, int(record_every), observe, sharp,
                            coulomb_only, jnp.int32(k))
        if bool(neighbors.overflowed(new.contacts, config)):
            contacts, config = neighbors.reallocate(
                state.contacts, detect.bounding_circles(state.blocks), config)
            state = state._replace(contacts=contacts)
            return None
        if not blocks_healthy(new.blocks, dt, config.skin):
            raise SimulationDiverged(int(state.step), state, stack_records(records))
        state = new
        return hist

    records, wall = run_in_chunks(chunk, n_steps, record_every, "blocks", progress)
    history = stack_records(records)
    history["wall_time"] = wall
    return state, history


def blocks_healthy(blocks: Blocks, dt, skin) -> bool:
    """The host loop's guard (host function): every float of the blocks finite,
    and no free block moving half the ``skin`` [m] in one step of ``dt`` [s]: it
    would outrun the pair list and could pass through another block (tunnelling)
    before the list sees the pair."""
    b = blocks
    free = np.asarray(b.valid & ~b.fixed)
    reach = np.asarray(jnp.sqrt(jnp.sum(b.vel ** 2, axis=1)) + jnp.abs(b.angvel) *
                       b.radius) * dt
    too_fast = bool(np.any(free & ~(reach < 0.5 * skin)))
    return not too_fast and all(bool(jnp.all(jnp.isfinite(x))) for x in
                                jax.tree_util.tree_leaves(b)
                                if jnp.issubdtype(x.dtype, jnp.floating))


def run_in_chunks(chunk, n_steps, record_every, desc, progress):
    """The host loop of :func:`run` and :func:`jdem.blocks.coupling.run`: records of
    ``record_every`` steps, at most 50 per chunk, with a progress bar.

    ``chunk(n, k, records)`` advances the caller's state by ``k <= n`` records and
    returns a history of ``n`` records of which the first ``k`` are real (every
    chunk has the same ``n``, so that one compiled program serves the whole run),
    or ``None`` when the chunk must run again (a list was grown); ``records`` are
    the chunks' histories so far (for the error it may raise to stop).  Returns
    ``(the chunks' histories as NumPy, wall time [s])``."""
    n_records = -(-int(n_steps) // int(record_every))
    per_chunk = max(1, min(n_records, 50))
    records = []
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_records * record_every, unit="step", desc=desc, leave=False)
    t0 = time.time()
    try:
        done = 0
        while done < n_records:
            k = min(per_chunk, n_records - done)
            hist = chunk(per_chunk, k, records)
            if hist is None:
                continue
            records.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:k], hist))
            done += k
            if bar is not None:
                bar.update(k * record_every)
    finally:
        if bar is not None:
            bar.close()
    return records, time.time() - t0


def stack_records(records):
    """One history dict from the chunks' records (``{}`` if there are none)."""
    return {key: np.concatenate([r[key] for r in records]) for key in records[0]} \
        if records else {}
