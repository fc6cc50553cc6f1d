"""State, parameter and configuration containers.

Citations ("002 eq 3") refer to the documents listed in REFERENCES.md.

jdem keeps three kinds of input apart (see the design notes):

* ``State``  — everything that evolves in time (particles, contacts, walls, bonds).
  Every array has a fixed capacity; padding rows are switched off by ``valid`` masks.
* ``Params`` — floats we may differentiate or ``vmap`` over (stiffnesses, friction,
  bond strengths, damping, the time step).  Every field is a JAX array.
* ``Config`` — static, hashable settings (dimension, capacities, contact model,
  the neighbour-search grid).  Changing it recompiles.

All containers are ``NamedTuple``s, hence JAX pytrees: ``state._replace(...)``
returns an updated copy, and ``jax.tree_util`` / ``jax.vmap`` see straight through.

Conventions
-----------
* SI units throughout.  2D discs have unit thickness (1 m), so 2D "areas" are
  lengths times 1 m and 2D stiffnesses are N/m per metre of thickness.
* ``d`` is the dimension (2 or 3).  Rotational quantities (angular velocity,
  torque, bond bending moment) have shape ``(N,)`` in 2D (about the out-of-plane
  axis) and ``(N, 3)`` in 3D.
* Normal forces are positive in compression, negative in tension (002 eq 3).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.validate import InputError, check_config, check_params, check_particle_input

Array = jnp.ndarray


def rot_shape(dim: int) -> tuple[int, ...]:
    """Trailing shape of one rotational quantity: ``()`` in 2D, ``(3,)`` in 3D."""
    return () if dim == 2 else (3,)


class Particles(NamedTuple):
    """Discs (2D) or spheres (3D); capacity ``N`` rows, of which ``valid`` are real.

    pos          (N, d)  centre position [m], to the nearest float of the working dtype
    pos_lo       (N, d)  the rest of the position [m]: the centre is pos + pos_lo
                         (compensated summation, :mod:`jdem.precision`)
    vel          (N, d)  translational velocity [m/s] (at the half step, leapfrog)
    angvel       (N,) or (N, 3)  angular velocity [rad/s]
    radius       (N,)    [m]
    mass         (N,)    inertial mass [kg] (may be density-scaled, 000 §3.3.2)
    gravity_mass (N,)    gravitational mass [kg]: the weight is gravity_mass * g
    inertia      (N,)    moment of inertia [kg m^2] (inertial, scaled with mass)
    material     (N,)    int index into the per-material arrays of ``Params``
    fixed_vel    (N, d)  bool: this velocity component is prescribed (kept as it is)
    fixed_rot    (N,) or (N, 3) bool: this angular-velocity component is prescribed
    ext_force    (N, d)  applied external force [N]
    ext_torque   (N,) or (N, 3) applied external torque [N m]
    valid        (N,)    bool: row holds a real particle
    """

    pos: Array
    pos_lo: Array
    vel: Array
    angvel: Array
    radius: Array
    mass: Array
    gravity_mass: Array
    inertia: Array
    material: Array
    fixed_vel: Array
    fixed_rot: Array
    ext_force: Array
    ext_torque: Array
    valid: Array


class Contacts(NamedTuple):
    """Neighbour list of candidate pairs (i < j) plus the unbonded contact history.

    i, j          (C,)   int32 particle indices; padding rows point at particle 0
    valid         (C,)   bool: row is a real candidate pair
    shear         (C, d) tangential contact force acting on particle i [N], global frame
    pos_at_build  (N, d) positions when the list was built (rebuild criterion)
    radius_at_build (N,) radii when the list was built (particles may grow)
    n_pairs       ()     int32 most pairs any build found since allocation (may exceed C)
    max_in_cell   ()     int32 fullest search cell any build saw since allocation
    n_builds      ()     int32 number of builds so far

    The list overflowed (some contact could have been missed) when
    ``n_pairs > C`` or ``max_in_cell > Config.max_per_cell``; see
    :func:`jdem.neighbors.overflowed`.  The host loop then re-allocates.
    """

    i: Array
    j: Array
    valid: Array
    shear: Array
    pos_at_build: Array
    radius_at_build: Array
    n_pairs: Array
    max_in_cell: Array
    n_builds: Array


class Walls(NamedTuple):
    """Rigid infinite planes; capacity ``W``.

    point        (W, d)  a point on the plane [m], to the nearest float
    point_lo     (W, d)  the rest of the point [m] (point + point_lo; :mod:`jdem.precision`)
    normal       (W, d)  unit normal pointing into the particle domain
    vel          (W, d)  wall velocity [m/s]; servo walls overwrite its normal part
    material     (W,)    int index into the per-material arrays of ``Params``
    servo        (W,)    bool: normal velocity servo-controlled to ``target_stress``
    target_stress (W,)   [Pa] compressive stress a servo wall holds (000 eq 4-69)
    area         (W,)    [m^2] (2D: length x 1 m) over which wall force makes stress
    servo_gain   (W,)    dimensionless relaxation factor (0 < alpha < 1)
    servo_vmax   (W,)    [m/s] cap on the servo wall speed
    force        (W, d)  force the particles exert on the wall at the last step [N]
    n_contacts   (W,)    int32 number of particles touching the wall at the last step
    shear        (W, N, d) tangential wall-contact force on each particle [N]
    valid        (W,)    bool
    """

    point: Array
    point_lo: Array
    normal: Array
    vel: Array
    material: Array
    servo: Array
    target_stress: Array
    area: Array
    servo_gain: Array
    servo_vmax: Array
    force: Array
    n_contacts: Array
    shear: Array
    valid: Array


class Bonds(NamedTuple):
    """Linked-bar bonds (002 §1); capacity ``B``.  Geometry-dependent stiffnesses
    (K_n, K_s, A_c, I, J; 002 eq 1, 2, 5) are recomputed from the radii and
    ``Params`` every step so that they stay differentiable; this holds only what
    evolves.

    i, j        (B,)    int32 particle indices (i < j)
    valid       (B,)    bool: row holds a bond (intact or broken)
    normal_force (B,)   F_n [N], positive in compression (002 eq 3)
    shear_force (B, d)  F_s acting on particle i [N], global frame
    twist       (B,)    twisting moment M_n [N m] (always 0 in 2D)
    bend        (B,) or (B, 3) bending moment M_s acting on particle i [N m]
    u_n         (B,)    total normal opening since bonding [m] (separation positive)
    u_s         (B, d)  total tangential displacement of i relative to j [m]
    alpha       (B,)    tensile damage 1 - T/T0 (002 eq 10)
    beta        (B,)    shear damage 1 - c/c0 (002 eq 10)
    moment_lost (B,)    bool: inequality 11 met; no more moment transmission
    broken      (B,)    bool: T or c reached zero; now a frictional contact
    break_mode  (B,)    int32 0 intact, 1 tension, 2 shear
    break_step  (B,)    int32 step at which it broke (-1 if intact)
    """

    i: Array
    j: Array
    valid: Array
    normal_force: Array
    shear_force: Array
    twist: Array
    bend: Array
    u_n: Array
    u_s: Array
    alpha: Array
    beta: Array
    moment_lost: Array
    broken: Array
    break_mode: Array
    break_step: Array


class State(NamedTuple):
    """The whole evolving state of one simulation.

    step   ()  int32 number of steps taken
    time   ()  simulated time [s]
    first_bad_step () int32 first step that failed the divergence guard
                   (jdem.integrate.healthy: non-finite, a particle moving over half its
                   radius in one step, a pair overlapping by over its smaller radius), -1 if none
    """

    particles: Particles
    contacts: Contacts
    walls: Walls
    bonds: Bonds
    step: Array
    time: Array
    first_bad_step: Array


class Params(NamedTuple):
    """Differentiable parameters.  Per-material arrays have length M (materials).

    dt               ()    time step [s]
    gravity          (d,)  [m/s^2]
    kn, ks           (M,)  linear contact normal / shear stiffness [N/m] (000 eq 4-1)
    friction         (M,)  Coulomb friction coefficient mu = tan(phi) of unbonded contacts
    youngs, poisson  (M,)  particle E [Pa] and nu for Hertz-Mindlin (000 eq 4-6, 4-8)
    contact_damping  ()    normal contact dashpot as a fraction of critical (0 = elastic)
    local_damping    ()    local non-viscous damping coefficient alpha (000 eq 3-19)
    viscous_damping  ()    mass-proportional viscous damping [1/s] (000 eq 3-9, alpha M)
    bond_youngs      ()    linked-bar E [Pa] (002 eq 2)
    bond_poisson     ()    linked-bar nu; G = E / (2 (1 + nu))
      (every ``bond_*`` field is either () for all bonds or, all of them
      together, (M,) per material: a bond between two materials is the bar of
      two halves in series with the weaker strengths, :func:`jdem.bond.bond_material`)
    bond_tensile     ()    initial tensile strength T0 [Pa] (002 eq 6)
    bond_cohesion    ()    initial cohesion c0 [Pa] (002 eq 8)
    bond_friction_angle () internal friction angle phi [rad] (002 eq 8)
    bond_tensile_strain () tensile fracture strain eps_lim (002 eq 6)
    bond_shear_strain   () shear fracture strain gamma_lim (002 eq 8)
    bond_damping     ()    normal and shear dashpots of intact bonds as a fraction of
                           critical, 2 zeta sqrt(m* K) (000 eq 3-1 applied to the bar
                           stiffnesses); damps relative motion only, so it neither
                           resists rigid motion nor adds a loading-rate stress at
                           quasi-static rates (0 = none)
    """

    dt: Array
    gravity: Array
    kn: Array
    ks: Array
    friction: Array
    youngs: Array
    poisson: Array
    contact_damping: Array
    local_damping: Array
    viscous_damping: Array
    bond_youngs: Array
    bond_poisson: Array
    bond_tensile: Array
    bond_cohesion: Array
    bond_friction_angle: Array
    bond_tensile_strain: Array
    bond_shear_strain: Array
    bond_damping: Array


CONTACT_MODELS = ("linear", "hertz")
FRICTION_RULE_NAMES = ("smaller", "mean", "geometric")  # jdem.contact.FRICTION_RULES
BOND_SECTIONS = ("circular", "slab")                     # jdem.bond.bond_geometry


@dataclasses.dataclass(frozen=True)
class Config:
    """Static settings; hashable, so usable as a ``jax.jit`` static argument.

    dim               2 (discs) or 3 (spheres)
    contact_model     "linear" (000 eq 4-1..4-3) or "hertz" (000 eq 4-6, 4-8)
    skin              neighbour-list skin [m]; rebuild when a particle moved skin/2
    cell_size         edge of a search cell [m]; >= largest diameter + skin
    grid_origin       lower corner of the search grid [m] (particles outside are
                      clamped into border cells, which stays correct)
    grid_shape        number of cells per axis
    max_per_cell      K, particles a cell can hold
    friction_mixing   friction of unlike materials (walls included, through their
                      material): "smaller" (default), "mean", "geometric", or a
                      symmetric M x M table (tuple of tuples) of coefficients,
                      which replaces ``Params.friction`` (not differentiated)
    bond_section      bending section of a 2D bond: "circular" (default: 002 eq 5,
                      I = pi min(2R1, 2R2)^4 / 64, as the seed) or "slab" (the
                      unit-thickness bar of a 2D model, I = 1 m x min(2R1, 2R2)^3 / 12).
                      The circular section is ~1.2e-3 of the slab's for 1 mm discs
                      and scales with the disc size in metres (not scale-free);
                      3D bonds are always circular.  The default is the seed's:
                      with it the strain-energy ratio follows the seed's law
                      lambda(N-bar) (002 eq 17) more closely at low N-bar
                      (experiments/results/coordination_study_small)

    The neighbour-list capacity C is the length of the ``Contacts`` arrays
    (a property of the state, not of the configuration).
    """

    dim: int = 2
    contact_model: str = "linear"
    skin: float = 1e-3
    cell_size: float = 1.0
    grid_origin: tuple = (0.0, 0.0)
    grid_shape: tuple = (1, 1)
    max_per_cell: int = 8
    friction_mixing: str | tuple = "smaller"
    bond_section: str = "circular"

    def __post_init__(self):
        if not isinstance(self.friction_mixing, str):   # a table: hashable tuples of floats
            try:
                table = tuple(tuple(float(v) for v in row) for row in self.friction_mixing)
            except (TypeError, ValueError):
                table = self.friction_mixing
            object.__setattr__(self, "friction_mixing", table)
        check_config(self, CONTACT_MODELS, FRICTION_RULE_NAMES)

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.grid_shape))

    def replace(self, **changes) -> "Config":
        return dataclasses.replace(self, **changes)

    def without_search_grid(self) -> "Config":
        """This configuration with the neighbour-search fields (skin, grid, cell
        capacity) at fixed values: the static key of a jitted function that
        applies the laws without searching for neighbours, so that it compiles
        once for every grid."""
        return self.replace(skin=1.0, cell_size=1.0, grid_origin=(0.0,) * self.dim,
                            grid_shape=(1,) * self.dim, max_per_cell=1)


def make_params(dim: int = 2, n_materials: int = 1, *, dt: float = 1e-6,
                gravity=None, kn=1e8, ks=None, friction=0.5, youngs=1e9, poisson=0.25,
                contact_damping=0.0, local_damping=0.0, viscous_damping=0.0,
                bond_youngs=10e9, bond_poisson=0.22, bond_tensile=3e6, bond_cohesion=3e6,
                bond_friction_angle=np.deg2rad(30.0), bond_tensile_strain=1e-3,
                bond_shear_strain=3e-3, bond_damping=0.0, dtype=None) -> Params:
    """Build a ``Params`` with every field a JAX array of the default float dtype.

    Per-material values may be scalars (broadcast to ``n_materials``) or sequences.
    ``ks`` defaults to ``kn`` (stiffness ratio 1, 000 eq 4-3).  Values are checked
    by :func:`jdem.validate.check_params`.
    """
    dtype = dtype or jnp.zeros(()).dtype
    f = lambda v: jnp.asarray(v, dtype=dtype)
    def per_mat(v, name):
        if np.ndim(v) > 0 and np.shape(v) != (n_materials,):
            raise InputError(f"{name} must be one value or one per material ({n_materials}), "
                             f"got shape {np.shape(v)}")
        return jnp.broadcast_to(f(v), (n_materials,)) + jnp.zeros((n_materials,), dtype)
    if gravity is None:
        gravity = np.zeros(dim)
    bond = dict(bond_youngs=bond_youngs, bond_poisson=bond_poisson, bond_tensile=bond_tensile,
                bond_cohesion=bond_cohesion, bond_friction_angle=bond_friction_angle,
                bond_tensile_strain=bond_tensile_strain, bond_shear_strain=bond_shear_strain,
                bond_damping=bond_damping)
    # one value for all bonds, or (any field given as a sequence) one per material
    per_material = any(np.ndim(v) > 0 for v in bond.values())
    params = Params(
        dt=f(dt), gravity=f(gravity), kn=per_mat(kn, "kn"),
        ks=per_mat(kn if ks is None else ks, "ks"), friction=per_mat(friction, "friction"),
        youngs=per_mat(youngs, "youngs"), poisson=per_mat(poisson, "poisson"),
        contact_damping=f(contact_damping), local_damping=f(local_damping),
        viscous_damping=f(viscous_damping),
        **{k: per_mat(v, k) if per_material else f(v) for k, v in bond.items()})
    check_params(params, dim)
    return params


def make_particles(pos, radius, *, density=2500.0, vel=None, angvel=None, material=None,
                   fixed_vel=None, fixed_rot=None, capacity=None, dtype=None) -> Particles:
    """Particles from centre positions ``(n, d)`` and radii ``(n,)``.

    Mass and moment of inertia follow from ``density`` [kg/m^3]: discs of unit
    thickness in 2D (m = rho pi r^2, I = m r^2 / 2), spheres in 3D
    (m = rho 4/3 pi r^3, I = 2/5 m r^2).  ``capacity`` >= n pads with invalid rows.
    Raises :class:`jdem.validate.InputError` naming the field and the value for
    an empty set, wrongly shaped arrays, negative / non-finite radii, negative
    material indices, coincident centres etc.
    """
    pos = np.asarray(pos, dtype=np.float64)
    radius = np.asarray(radius, dtype=np.float64)
    n, dim = pos.shape if pos.ndim == 2 else (None, None)
    check_particle_input(pos, radius, density, vel=vel, angvel=angvel, material=material,
                         fixed_vel=fixed_vel, fixed_rot=fixed_rot)
    capacity = n if capacity is None else int(capacity)
    if capacity < n:
        raise InputError(f"capacity must be >= the number of particles {n}, got {capacity}")
    rs = rot_shape(dim)
    density = np.broadcast_to(np.asarray(density, dtype=np.float64), (n,))
    if dim == 2:
        mass = density * np.pi * radius**2
        inertia = 0.5 * mass * radius**2
    else:
        mass = density * 4.0 / 3.0 * np.pi * radius**3
        inertia = 0.4 * mass * radius**2

    def pad(a, fill, shape_tail, dt):
        out = np.full((capacity,) + shape_tail, fill, dtype=dt)
        if a is not None:
            out[:n] = np.asarray(a, dtype=dt).reshape((n,) + shape_tail)
        return out

    dtype = dtype or jnp.zeros(()).dtype
    fl = np.dtype(dtype)
    # padding rows: radius 0 (never touch anything), mass 1 (divisions stay finite)
    parts = Particles(
        pos=pad(pos, 0.0, (dim,), fl),
        pos_lo=pad(None, 0.0, (dim,), fl),
        vel=pad(vel, 0.0, (dim,), fl),
        angvel=pad(angvel, 0.0, rs, fl),
        radius=pad(radius, 0.0, (), fl),
        mass=pad(mass, 1.0, (), fl),
        gravity_mass=pad(mass, 0.0, (), fl),
        inertia=pad(inertia, 1.0, (), fl),
        material=pad(material, 0, (), np.int32),
        fixed_vel=pad(fixed_vel, False, (dim,), bool),
        fixed_rot=pad(fixed_rot, False, rs, bool),
        ext_force=pad(None, 0.0, (dim,), fl),
        ext_torque=pad(None, 0.0, rs, fl),
        valid=np.arange(capacity) < n,
    )
    return Particles(*[jnp.asarray(a) for a in parts])


def make_walls(points, normals, *, dim=None, n_particles, vel=None, material=None, servo=None,
               target_stress=None, area=None, servo_gain=0.5, servo_vmax=1.0,
               dtype=None) -> Walls:
    """Rigid planes from points ``(W, d)`` on them and normals ``(W, d)`` pointing
    into the domain (normalised here).  ``n_particles`` is the particle capacity N
    (for the per-particle wall-contact history)."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    normals = np.atleast_2d(np.asarray(normals, dtype=np.float64))
    w, d = points.shape
    if dim is not None and d != dim:
        raise ValueError(f"wall points have dimension {d}, expected {dim}")
    if normals.shape != points.shape:
        raise ValueError(f"wall normals shape {normals.shape} != points shape {points.shape}")
    norm = np.linalg.norm(normals, axis=1)
    if np.any(~np.isfinite(norm)) or np.any(norm == 0):
        raise ValueError(f"wall normals must be finite and non-zero, got {normals.tolist()}")
    dtype = dtype or jnp.zeros(()).dtype
    fl = np.dtype(dtype)
    full = lambda v, dflt, dt: np.broadcast_to(np.asarray(dflt if v is None else v, dtype=dt), (w,)).copy()
    walls = Walls(
        point=points.astype(fl),
        point_lo=np.zeros((w, d), fl),
        normal=(normals / norm[:, None]).astype(fl),
        vel=(np.zeros((w, d)) if vel is None else np.asarray(vel, dtype=np.float64).reshape(w, d)).astype(fl),
        material=full(material, 0, np.int32),
        servo=full(servo, False, bool),
        target_stress=full(target_stress, 0.0, fl),
        area=full(area, 1.0, fl),
        servo_gain=full(servo_gain, 0.5, fl),
        servo_vmax=full(servo_vmax, 1.0, fl),
        force=np.zeros((w, d), fl),
        n_contacts=np.zeros((w,), np.int32),
        shear=np.zeros((w, n_particles, d), fl),
        valid=np.ones((w,), bool),
    )
    return Walls(*[jnp.asarray(a) for a in walls])


def no_walls(dim: int, n_particles: int, dtype=None) -> Walls:
    """An empty wall set (capacity 0)."""
    dtype = dtype or jnp.zeros(()).dtype
    z = lambda *s, dt=dtype: jnp.zeros(s, dt)
    return Walls(point=z(0, dim), point_lo=z(0, dim), normal=z(0, dim), vel=z(0, dim),
                 material=z(0, dt=jnp.int32),
                 servo=z(0, dt=bool), target_stress=z(0), area=z(0), servo_gain=z(0),
                 servo_vmax=z(0), force=z(0, dim), n_contacts=z(0, dt=jnp.int32),
                 shear=z(0, n_particles, dim), valid=z(0, dt=bool))


ROW_ALIGN = 64   #: default capacities of bond and contact lists are multiples of this


def aligned_rows(n: int) -> int:
    """``n`` rounded up to a multiple of :data:`ROW_ALIGN`: the row capacity the
    bond and neighbour lists get by default (:func:`jdem.bond.bonds_for_pairs`,
    :func:`jdem.neighbors.room_for`, :func:`jdem.neighbors.dense_capacity`).

    XLA:CPU runs the per-row kernels over an odd number of rows several times
    slower than over an even number (measured on a 2-core CPU, the 3D bond law
    of 64,489 bonds in a 20-call loop: 7.8-12 ms per call; the same bonds with
    one padding row, 64,490 rows: 2.6-4.3 ms).  Padding rows are invalid and
    cost a few per cent at most.
    """
    n = int(n)
    return -(-n // ROW_ALIGN) * ROW_ALIGN


def empty_bonds(dim: int, capacity: int = 0, dtype=None) -> Bonds:
    """A bond set with ``capacity`` rows, all invalid."""
    dtype = dtype or jnp.zeros(()).dtype
    z = lambda *s, dt=dtype: jnp.zeros(s, dt)
    rs = rot_shape(dim)
    return Bonds(i=z(capacity, dt=jnp.int32), j=z(capacity, dt=jnp.int32),
                 valid=z(capacity, dt=bool), normal_force=z(capacity),
                 shear_force=z(capacity, dim), twist=z(capacity), bend=z(capacity, *rs),
                 u_n=z(capacity), u_s=z(capacity, dim), alpha=z(capacity), beta=z(capacity),
                 moment_lost=z(capacity, dt=bool), broken=z(capacity, dt=bool),
                 break_mode=z(capacity, dt=jnp.int32),
                 break_step=jnp.full((capacity,), -1, jnp.int32))
