"""Platen tests: uniaxial compression, biaxial / triaxial compression with
servo-controlled confinement, and the Brazilian splitting test (002 §2).
Citations ("000 eq 4-69") refer to the documents listed in REFERENCES.md.

Geometry.  The loading axis is the last axis (y in 2D, z in 3D).  Rigid planar
walls (:func:`jdem.state.make_walls`, material ``PLATEN`` = 1) touch the
specimen: wall 0 is the bottom platen (fixed), wall 1 the top platen (moving
towards the specimen), and for a biaxial (2D) / triaxial (3D) test walls 2, 3
(and 4, 5 in 3D) are lateral walls servo-controlled to the confining stress
(000 eq 4-69) over the current height times the other lateral extent.  Every
wall starts on the outermost particle edge.  With confinement, the test starts
with an isotropic preload (the top platen servo-controlled to the confining
stress too), then the top platen is driven; ``h0`` and ``w0`` are taken at the
end of the preload, inside the run, so the preload is part of the
differentiable curve.

Loading rate.  The top platen's full speed is ``loading_rate`` times the bar
wave speed c = sqrt(E / rho): the axial strain added while a wave crosses the
specimen once.  The number of wave transits to the peak (eps_peak / rate)
does not depend on the specimen's size, so one default serves every size
(the steps needed grow with the height in particles).  ``platen_step`` [m per
step] may be given instead.  The platen speeds up over ``ramp_transits`` wave
transits (half a cosine): a sudden start rings the specimen.

Units: SI; 2D discs have unit thickness (areas in m^2 per m).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import bond as bond_mod
from jdem import measure, precision, timestep
from jdem.batch import broadcast_batch, is_batched, member, stack_states
from jdem.lab import damping as damping_mod
from jdem.lab.core import LabTest, Plan, Setup, in_precision, n_records_for, ramp
from jdem.materials import PLATEN, rock_bond_value
from jdem.simulate import make_state
from jdem.specimen import as_arrays
from jdem.state import make_walls
from jdem.validate import InputError

N_SLICES = 32                    #: horizontal slices of the lateral-extent measurement
DEFAULT_LOADING_RATE = 4e-6      #: platen speed / wave speed (see the module docstring)
DEFAULT_RAMP_TRANSITS = 10.0     #: wave transits over which the platen speeds up
DEFAULT_PRELOAD_TRANSITS = 40.0  #: wave transits of the isotropic preload
DEFAULT_RECORDS = 200            #: records of the loading phase when record_every is not given


class PlatenFrame(NamedTuple):
    """Reference geometry and loading of a platen test (arrays; a leading member
    axis for an ensemble).

    h0          initial platen distance [m] (a preloaded test measures its own at
                the end of the preload), less the thickness of bonded loading
                plates (``info["plate_thickness"]``, jdem.specimen.add_plates)
    w0          (d-1,) initial lateral extents [m] (slices of the packing; with
                lateral walls their distance)
    area        platen area [m^2] of the axial stress (2D: width x 1 m; Brazilian: 1,
                so that the axial stress is the load per metre)
    diameter    Brazilian disc diameter D [m] (0 otherwise)
    velocity    (W, d) wall velocities at full loading speed [m/s]
    background  background damping coefficient [1/s] (:mod:`jdem.lab.damping`)
    gauge       (N, d-1) weights of the lateral gauge particles (:func:`lateral_gauges`)
    gauge_w0    (d-1,) initial gauge widths [m]
    wall0       (W, d) wall points at set-up [m]: the records hold each wall's
                displacement from here (:mod:`jdem.precision`: a float32 displacement
                keeps sub-nanometre steps that a float32 coordinate rounds away)
    pos0        (N, d-1) lateral particle coordinates at set-up [m] (the gauges'
                reference, likewise)
    """

    h0: jnp.ndarray
    w0: jnp.ndarray
    area: jnp.ndarray
    diameter: jnp.ndarray
    velocity: jnp.ndarray
    background: jnp.ndarray
    gauge: jnp.ndarray
    gauge_w0: jnp.ndarray
    wall0: jnp.ndarray
    pos0: jnp.ndarray


# ----------------------------------------------------------------------------- measurement
def slice_widths(particles, dim):
    """Lateral extent of the packing: the loading axis is cut into ``N_SLICES``
    equal slices between the lowest and highest particle centre; in each slice the
    extent along each lateral axis is max(x + r) - min(x - r) over its particles;
    the widths are the mean over the non-empty slices.  Returns (dim - 1,)."""
    p = particles
    valid = p.valid
    ax = dim - 1
    z = p.pos[:, ax]
    zmin = jnp.min(jnp.where(valid, z, jnp.inf))
    zmax = jnp.max(jnp.where(valid, z, -jnp.inf))
    span = jnp.where(zmax > zmin, zmax - zmin, 1.0)
    b = jnp.clip(jnp.floor((z - zmin) / span * N_SLICES), 0, N_SLICES - 1).astype(jnp.int32)
    b = jnp.where(valid, b, N_SLICES)
    out = []
    for a in range(dim - 1):
        lo = jax.ops.segment_min(jnp.where(valid, p.pos[:, a] - p.radius, jnp.inf), b,
                                 num_segments=N_SLICES + 1)[:N_SLICES]
        hi = jax.ops.segment_max(jnp.where(valid, p.pos[:, a] + p.radius, -jnp.inf), b,
                                 num_segments=N_SLICES + 1)[:N_SLICES]
        ok = jnp.isfinite(lo) & jnp.isfinite(hi)
        out.append(jnp.sum(jnp.where(ok, hi - lo, 0.0)) / jnp.maximum(jnp.sum(ok), 1))
    return jnp.stack(out)


def lateral_gauges(particles, dim):
    """The lateral strain gauges of a free-sided specimen (host, NumPy): on each
    side, the particles of the middle half of the height whose outer edge lies
    within one largest radius of that side's outermost edge, fixed at set-up
    (a gauge glued at mid-height, away from the platens' end effects).  The
    gauge width along lateral axis a is mean(x_a + r) over the far side's set
    minus mean(x_a - r) over the near side's: a mean over fixed particles, so it
    is smooth in time and in the parameters, and it follows the specimen's
    surface past the peak instead of jumping with its outermost fragment.

    Returns ``(gauge, w0)``: (N, d-1) weights (1/n on the far side, -1/n on the
    near side, 0 elsewhere) and (d-1,) initial gauge widths [m]."""
    pos = np.asarray(particles.pos, np.float64)
    r = np.asarray(particles.radius, np.float64)
    valid = np.asarray(particles.valid, bool)
    ax = dim - 1
    zlo, zhi = extent(particles, ax)
    z = pos[:, ax]
    mid = valid & (z >= zlo + 0.25 * (zhi - zlo)) & (z <= zlo + 0.75 * (zhi - zlo))
    if not np.any(mid):
        mid = valid
    r_max = float(np.max(r[valid]))
    gauge = np.zeros((pos.shape[0], dim - 1))
    w0 = np.zeros(dim - 1)
    for a in range(dim - 1):
        far = mid & (pos[:, a] + r >= np.max((pos[:, a] + r)[mid]) - r_max)
        near = mid & (pos[:, a] - r <= np.min((pos[:, a] - r)[mid]) + r_max)
        gauge[far, a] = 1.0 / np.sum(far)
        gauge[near, a] = -1.0 / np.sum(near)
        w0[a] = np.mean((pos[:, a] + r)[far]) - np.mean((pos[:, a] - r)[near])
    return gauge, w0


def gauge_change(particles, gauge, pos0):
    """(d-1,) change of the gauge widths [m] since set-up (traced): the gauge
    weights applied to the particles' lateral displacements from ``pos0``
    (N, d-1), summed with compensation (:mod:`jdem.precision`)."""
    d1 = gauge.shape[-1]
    p = particles
    disp = precision.difference(p.pos[:, :d1], p.pos_lo[:, :d1], pos0, 0.0)
    return jnp.sum(gauge * disp, axis=0)


def observe(state, params, config, frame):
    """One record of a platen test: ``step``; per wall (W,): ``wall_disp``
    (displacement along its normal axis since set-up [m]), ``wall_force``
    (compressive normal force [N]) and ``wall_area``; ``width``
    (:func:`slice_widths`), ``gauge_change`` (:func:`gauge_change`); ``stress_sum``, the
    averaged-stress sum of :func:`jdem.measure.averaged_stress` with volume 1;
    bond counts of the rock (bonds to plate discs, which have the platens'
    material, not counted); bond, contact and kinetic energies."""
    w = state.walls
    stats = bond_mod.bond_stats(state.bonds, bond_mod.rock_bonds(state.bonds, state.particles,
                                                                 w.material[0]))
    axis_of = jnp.argmax(jnp.abs(w.normal), axis=-1)
    return dict(
        step=state.step,
        wall_disp=jnp.take_along_axis(precision.difference(w.point, w.point_lo, frame.wall0, 0.0),
                                      axis_of[:, None], axis=-1)[:, 0],
        wall_force=-jnp.sum(w.force * w.normal, axis=-1),
        wall_area=w.area,
        width=slice_widths(state.particles, config.dim),
        gauge_change=gauge_change(state.particles, frame.gauge, frame.pos0),
        stress_sum=measure.averaged_stress(state, params, config, 1.0),
        fracture_degree=stats["fracture_degree"],
        n_broken=stats["n_broken"], n_tension=stats["n_tension"], n_shear=stats["n_shear"],
        bond_energy=bond_mod.bond_strain_energy(state.bonds, state.particles, params,
                                                config.dim),
        contact_energy=measure.contact_energy(state, params, config),
        kinetic_energy=measure.kinetic_energy(state),
    )


def derive(raw: dict, frame: PlatenFrame, plan: Plan, volume_of=None) -> dict:
    """History of a platen test from its records (records on axis 0, then any
    member axis); preload records are dropped.  Entries:

    step               step number
    height             distance between the platens [m]
    axial_strain       (h0 - H) / h0 (compression positive)
    axial_stress       compressive force on the top platen / ``frame.area`` [Pa]
    bottom_stress      the same on the bottom platen (equal at equilibrium)
    width              (..., d-1) lateral extent [m]: the lateral walls' distance
                       with confinement, else :func:`slice_widths`
    lateral_strain     compression positive (negative when the specimen bulges),
                       mean over lateral axes: with confinement (w0 - w) / w0 of
                       the lateral walls, else of the mid-height gauges
                       (:func:`lateral_gauges`)
    volumetric_strain  axial_strain + sum of lateral strains (small strains)
    lateral_stress     with confinement: mean compressive stress on the lateral walls
    volume             H x area x (w / w0) per lateral axis [m^3]
    avg_stress         (..., d, d) averaged stress tensor (000 eq 4-44) with
                       ``volume``, compression positive; ``avg_stress_axial``,
                       ``avg_stress_lateral`` its axial and mean lateral entries
    fracture_degree, n_broken, n_tension, n_shear   bond counts (002 §2.3)
    bond_energy, contact_energy, kinetic_energy     [J]
    kinetic_ratio      kinetic / (bond + contact) energy: the in-run quasi-static
                       indicator (:mod:`jdem.lab.summary`)
    """
    dim = plan.config.dim
    n_lat = int(plan.option("n_lateral", 0))
    pre = plan.preload_records
    # strains from the walls' displacements, not from differences of their
    # coordinates (which float32 holds only to ~4 nm at 5 cm; jdem.precision)
    disp = raw["wall_disp"]
    h0, w0 = frame.h0, frame.w0
    if pre:   # the loading starts from the end of the preload
        ref = disp[pre - 1]
        h0 = h0 + (ref[..., 1] - ref[..., 0])
        w0 = jnp.stack([frame.w0[..., a] + (ref[..., 3 + 2 * a] - ref[..., 2 + 2 * a])
                        for a in range(dim - 1)], axis=-1)
        raw = {k: v[pre:] for k, v in raw.items()}
        disp = raw["wall_disp"] - ref[None]
    h0 = jax.lax.stop_gradient(h0)
    h = {"step": raw["step"]}
    shortening = disp[..., 0] - disp[..., 1]
    height = h0 - shortening
    h["height"] = height
    h["axial_strain"] = jax.lax.stop_gradient(shortening / h0)
    force = raw["wall_force"]
    h["axial_stress"] = force[..., 1] / frame.area
    h["bottom_stress"] = force[..., 0] / frame.area
    w0 = jax.lax.stop_gradient(w0)
    if n_lat:
        narrowing = jnp.stack([disp[..., 2 + 2 * a] - disp[..., 3 + 2 * a]
                               for a in range(dim - 1)], axis=-1)
        width = w0[None] - narrowing
        lat = force[..., 2:2 + n_lat] / raw["wall_area"][..., 2:2 + n_lat]
        h["lateral_stress"] = jnp.mean(lat, axis=-1)
    else:
        width = raw["width"]
    h["width"] = width
    if n_lat:
        lat_strain = narrowing / w0[None]
    else:
        g0 = jax.lax.stop_gradient(frame.gauge_w0)[None]
        lat_strain = -raw["gauge_change"] / g0
    h["lateral_strain"] = jnp.mean(lat_strain, axis=-1)
    h["volumetric_strain"] = h["axial_strain"] + jnp.sum(lat_strain, axis=-1)
    volume = (volume_of or box_volume)(height, width, frame)
    h["volume"] = volume
    sig = raw["stress_sum"] / volume[..., None, None]
    h["avg_stress"] = sig
    h["avg_stress_axial"] = sig[..., dim - 1, dim - 1]
    h["avg_stress_lateral"] = jnp.mean(jnp.stack([sig[..., a, a] for a in range(dim - 1)]),
                                       axis=0)
    for k in ("fracture_degree", "n_broken", "n_tension", "n_shear", "bond_energy",
              "contact_energy", "kinetic_energy"):
        h[k] = raw[k]
    strain_energy = raw["bond_energy"] + raw["contact_energy"]
    h["kinetic_ratio"] = raw["kinetic_energy"] / jnp.maximum(strain_energy, 1e-300)
    return h


def derive_brazilian(raw: dict, frame: PlatenFrame, plan: Plan) -> dict:
    """:func:`derive` plus ``load`` P [N per m] (top platen force) and
    ``tensile_strength_indirect`` sigma_t = 2 P / (pi D t), t = 1 m (the
    indirect tensile strength of the Brazilian test)."""
    h = derive(raw, frame, plan, disc_volume)
    h["load"] = h["axial_stress"] * frame.area
    h["tensile_strength_indirect"] = 2.0 * h["load"] / (jnp.pi * frame.diameter)
    return h


def box_volume(height, width, frame):
    """H x area x (w / w0) per lateral axis [m^3]."""
    return height * frame.area * jnp.prod(width / frame.w0[None], axis=-1)


def disc_volume(height, width, frame):
    """pi D^2 / 4 x 1 m [m^3] (a Brazilian disc)."""
    return jnp.pi * frame.diameter ** 2 / 4.0 * jnp.ones_like(height)


# ----------------------------------------------------------------------------- traced loading
def load(state, k, frame: PlatenFrame, plan: Plan):
    """Record ``k``: wall velocities along the ramp, the top platen servo-controlled
    during the preload, the lateral servo areas from the current geometry."""
    w = state.walls
    vel = frame.velocity * ramp(k, plan).astype(frame.velocity.dtype)
    servo = w.servo
    if plan.preload_records:
        servo = servo.at[..., 1].set(jnp.asarray(k) < plan.preload_records)
    n_lat = int(plan.option("n_lateral", 0))
    area = w.area
    if n_lat:
        dim = plan.config.dim
        ax = dim - 1
        pos = w.point
        height = pos[..., 1, ax] - pos[..., 0, ax]
        widths = [pos[..., 3 + 2 * a, a] - pos[..., 2 + 2 * a, a] for a in range(dim - 1)]
        for j in range(n_lat):
            other = [widths[b] for b in range(dim - 1) if b != j // 2]
            val = height * (math.prod(other) if other else 1.0)
            area = area.at[..., 2 + j].set(val)
    return state._replace(walls=w._replace(vel=vel, servo=servo, area=area))


def boundary(state, params, frame: PlatenFrame):
    """Background damping against the affine field of the driven platens.

    The reference is the platens' *prescribed* motion: a servo-controlled wall
    (the top platen during a preload or in a stress-controlled test) counts as
    at rest, since its servo speed (up to ``servo_vmax``) is a control
    signal, not a motion the specimen should follow.  Lateral walls are servo
    walls, so the lateral components are not background-damped."""
    w = state.walls
    ax = state.particles.pos.shape[-1] - 1
    v_lo = jnp.where(w.servo[0], 0.0, w.vel[0, ax])
    v_hi = jnp.where(w.servo[1], 0.0, w.vel[1, ax])
    f, t = damping_mod.affine_force(state.particles, frame.background, ax, w.point[0, ax],
                                    v_lo, w.point[1, ax], v_hi)
    return state, f, t


# ----------------------------------------------------------------------------- host set-up
def extent(particles, axis):
    """(min, max) of x - r, x + r over the valid particles along ``axis`` [m]."""
    p = np.asarray(particles.pos, np.float64)
    r = np.asarray(particles.radius, np.float64)
    v = np.asarray(particles.valid, bool)
    return float(np.min(p[v, axis] - r[v])), float(np.max(p[v, axis] + r[v]))


def bulk_density(particles) -> float:
    """Mass over solid volume of the valid particles [kg/m^3] (2D: unit thickness)."""
    v = np.asarray(particles.valid, bool)
    r = np.asarray(particles.radius, np.float64)[v]
    vol = np.pi * r ** 2 if particles.pos.shape[1] == 2 else 4.0 / 3.0 * np.pi * r ** 3
    return float(np.sum(np.asarray(particles.mass, np.float64)[v]) / np.sum(vol))


def _walls_around(particles, confining, platen_material, servo_vmax):
    dim = int(particles.pos.shape[1])
    ax = dim - 1
    e = np.eye(dim)
    lo_ax, hi_ax = extent(particles, ax)
    points, normals = [e[ax] * lo_ax, e[ax] * hi_ax], [e[ax], -e[ax]]
    n_lat = 0
    if confining:
        for a in range(dim - 1):
            lo, hi = extent(particles, a)
            points += [e[a] * lo, e[a] * hi]
            normals += [e[a], -e[a]]
        n_lat = 2 * (dim - 1)
    n_w = 2 + n_lat
    widths = [hi - lo for lo, hi in (extent(particles, a) for a in range(dim - 1))]
    h_box = hi_ax - lo_ax
    servo = np.zeros(n_w, bool)
    target = np.zeros(n_w)
    area = np.ones(n_w)
    area[:2] = float(np.prod(widths))
    if confining:
        servo[2:] = True
        target[1:] = confining          # the top platen holds it during the preload
        for k in range(n_lat):
            a = k // 2
            area[2 + k] = h_box * float(np.prod([w for b, w in enumerate(widths) if b != a]))
    walls = make_walls(np.asarray(points), np.asarray(normals),
                       n_particles=int(particles.pos.shape[0]),
                       material=np.full(n_w, platen_material), servo=servo,
                       target_stress=target, area=area, servo_vmax=servo_vmax)
    return walls, h_box, widths, n_lat


def _critical_dt(state, config, params_members, particles):
    r_small = float(np.min(np.asarray(particles.radius)[np.asarray(particles.valid)]))
    w = state.walls
    probe = state._replace(walls=w._replace(point=w.point + 1e-3 * r_small * w.normal))
    return min(float(timestep.critical_timestep(probe, m, config)) for m in params_members)


def platen_setup(test: LabTest, specimens, params, *, max_strain=3e-3, loading_rate=None,
                 platen_step=None, confining_stress=None, damping=None, record_every=None,
                 ramp_transits=DEFAULT_RAMP_TRANSITS, preload_transits=DEFAULT_PRELOAD_TRANSITS,
                 dt=None, stiffness_margin=1.0, platen_material=PLATEN, diameter=None,
                 disc=False, top_stress=None, bond_section="circular",
                 precision=precision.DEFAULT) -> Setup:
    """Build a platen test (see the test objects :data:`UCS`, :data:`BIAXIAL`,
    :data:`BRAZILIAN` for the arguments; ``bond_section`` is the 2D bonds'
    bending section, :class:`jdem.state.Config`; ``precision`` "float32"
    (default) or "float64", :mod:`jdem.precision`: the set-up is built in
    float64 when JAX runs with x64, then cast)."""
    damping = damping_mod.check(damping_mod.smooth() if damping is None else damping)
    single = hasattr(specimens, "particles") or (isinstance(specimens, tuple)
                                                 and not hasattr(specimens[0], "particles")
                                                 and len(specimens) in (2, 3))
    members = [specimens] if single else list(specimens)
    if not members:
        raise InputError("specimens is empty")
    if not (np.isfinite(max_strain) and max_strain > 0):
        raise InputError(f"max_strain must be > 0, got {max_strain!r}")
    if loading_rate is not None and platen_step is not None:
        raise InputError("give loading_rate or platen_step, not both")
    if confining_stress is not None and not (np.isfinite(confining_stress)
                                             and confining_stress > 0):
        raise InputError(f"confining_stress must be > 0 (or None), got {confining_stress!r}")
    if not stiffness_margin >= 1.0:
        raise InputError(f"stiffness_margin must be >= 1, got {stiffness_margin!r}")
    if record_every is not None and int(record_every) < 1:
        raise InputError(f"record_every must be >= 1, got {record_every!r}")
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=jnp.asarray(a).dtype), params)
    if np.shape(params.kn)[-1] <= platen_material:
        raise InputError(f"params has {np.shape(params.kn)[-1]} materials; the platens use "
                         f"material {platen_material} (see jdem.materials.rock_params)")
    batched_params = is_batched(params)
    n_par = int(np.shape(params.dt)[0]) if batched_params else 1
    if batched_params and len(members) > 1 and len(members) != n_par:
        raise InputError(f"{len(members)} specimens but {n_par} parameter sets")
    par_members = [member(params, b) for b in range(n_par)] if batched_params else [params]
    steps = None
    if platen_step is not None:
        steps = np.atleast_1d(np.asarray(platen_step, np.float64))
        if steps.ndim != 1 or not np.all(np.isfinite(steps) & (steps > 0)):
            raise InputError(f"platen_step must be a length > 0 (or one per member), got "
                             f"{platen_step!r}")
        if steps.size > 1 and steps.size != max(n_par, len(members)):
            raise InputError(f"platen_step has {steps.size} values for "
                             f"{max(n_par, len(members))} members")
    rate = DEFAULT_LOADING_RATE if loading_rate is None and steps is None else loading_rate
    if rate is not None and not (np.isfinite(rate) and rate > 0):
        raise InputError(f"loading_rate must be > 0, got {loading_rate!r}")
    youngs = float(np.max(np.asarray(rock_bond_value(params, "bond_youngs"))))
    built = []
    for m in members:
        particles, bonds, info = as_arrays(m)
        # servo speed cap under smooth damping: a wall arriving at v_max hits with
        # rho c v_max, kept at a tenth of the stress it controls (faster, it rings
        # the lightly damped specimen; local damping absorbs it, 1 m/s as before)
        held = max(float(confining_stress or 0.0), float(top_stress or 0.0))
        rho_m = bulk_density(particles)
        vmax = 0.1 * held / (rho_m * math.sqrt(youngs / rho_m)) \
            if held > 0 and damping.kind == "smooth" else 1.0
        if int(particles.pos.shape[1]) != params.gravity.shape[-1]:
            raise InputError(f"specimen has dimension {particles.pos.shape[1]}, params "
                             f"{params.gravity.shape[-1]}")
        walls, h_box, widths, n_lat = _walls_around(particles, confining_stress,
                                                    platen_material, vmax)
        if top_stress is not None:   # the top platen held at a stress, not driven
            walls = walls._replace(servo=walls.servo.at[1].set(True),
                                   target_stress=walls.target_stress.at[1].set(top_stress))
        state, config = make_state(particles, walls=walls, bonds=bonds)
        config = config.replace(bond_section=bond_section)
        built.append((particles, info, state, config, h_box, widths, n_lat))
    dim = int(built[0][0].pos.shape[1])
    ax = dim - 1
    stiff = [p._replace(bond_youngs=p.bond_youngs * stiffness_margin,
                        kn=p.kn * stiffness_margin, ks=p.ks * stiffness_margin)
             for p in par_members]
    if dt is None:
        dt = min(timestep.recommended(_critical_dt(st, cfg, stiff, pa))
                 for pa, _, st, cfg, *_ in built)
    dt = float(dt)
    params = damping_mod.damped_params(params, damping)
    params = params._replace(dt=jnp.full(np.shape(params.dt), dt, jnp.asarray(params.dt).dtype))

    # per member: its own wave speed (so every member loads at the same rate in
    # transits), platen speed and background damping
    heights = np.array([b[4] for b in built])
    rhos = np.array([bulk_density(b[0]) for b in built])
    waves = np.sqrt(youngs / rhos)
    n_mem = max(n_par, len(members))
    if steps is None:
        steps = rate * waves * dt                      # one per specimen
    per_member = np.broadcast_to(steps, (len(members),)) if steps.size > 1 and \
        len(members) > 1 else np.broadcast_to(steps[:1], (len(members),))
    transit_steps = float(np.max(heights / (waves * dt)))
    load_steps = float(np.max(max_strain * heights / per_member))
    if steps.size > 1 and len(members) == 1:
        load_steps = max_strain * float(heights[0]) / float(np.min(steps))
    ramp_steps = ramp_transits * transit_steps
    pre_steps = preload_transits * transit_steps if confining_stress else 0.0
    if record_every is None:
        record_every = max(1, int((load_steps + 0.5 * ramp_steps) / DEFAULT_RECORDS))
    record_every = int(record_every)
    ramp_records = int(math.ceil(ramp_steps / record_every))
    pre_records = int(math.ceil(pre_steps / record_every))
    n_records = n_records_for(load_steps, record_every, ramp_records, pre_records)

    frames = []
    n_cap = max(int(b[2].particles.pos.shape[0]) for b in built)   # stack_states pads to it
    for k, (particles, info, state, config, h_box, widths, n_lat) in enumerate(built):
        vel = np.zeros(np.shape(state.walls.vel))
        vel[1, ax] = 0.0 if top_stress is not None else -float(per_member[k]) / dt
        w0 = np.asarray(slice_widths(particles, dim)) if not n_lat else np.asarray(widths)
        diam = 0.0
        if disc:
            diam = float(diameter) if diameter is not None else float(
                2.0 * info["radius"]) if "radius" in info else h_box
        gauge, gauge_w0 = lateral_gauges(particles, dim)
        gauge = np.pad(gauge, ((0, n_cap - gauge.shape[0]), (0, 0)))
        # bonded loading plates (jdem.specimen.add_plates): strains over the rock
        h_rock = h_box - 2.0 * float(info.get("plate_thickness", 0.0))
        frames.append(PlatenFrame(
            h0=np.asarray(h_rock), w0=np.asarray(w0, np.float64),
            area=np.asarray(1.0 if disc else float(np.prod(widths))),
            diameter=np.asarray(diam), velocity=vel,
            background=np.asarray(damping_mod.background_coefficient(
                damping, youngs, rhos[k], h_box)),
            gauge=gauge, gauge_w0=gauge_w0, wall0=np.asarray(state.walls.point, np.float64),
            pos0=np.pad(np.asarray(particles.pos, np.float64)[:, :dim - 1],
                        ((0, n_cap - int(particles.pos.shape[0])), (0, 0)))))
    dtype = jnp.asarray(params.dt).dtype
    n_lat = built[0][6]
    if len(members) > 1:
        state, config = stack_states([b[2] for b in built], dim)
        frame = jax.tree_util.tree_map(lambda *a: np.stack(a), *frames)
    else:
        state, config = built[0][2], built[0][3]
        frame = frames[0]
        if batched_params:
            state = broadcast_batch(state, n_par)
            frame = jax.tree_util.tree_map(lambda a: np.broadcast_to(a, (n_par,) + a.shape),
                                           frame)
    batched = len(members) > 1 or batched_params
    if steps.size > 1 and len(members) == 1:   # one platen speed per parameter set
        vel = np.array(frame.velocity)
        vel[:, 1, ax] = -steps / dt
        frame = frame._replace(velocity=vel)
    frame = jax.tree_util.tree_map(lambda a: jnp.asarray(np.array(a), dtype), frame)
    plan = Plan(test=test, config=config, n_records=n_records, record_every=record_every,
                preload_records=pre_records, ramp_records=ramp_records, batched=batched,
                damping=damping,
                options=(("n_lateral", n_lat),
                         ("loading_rate", float(np.min(np.asarray(steps) / dt / waves.max()))),
                         ("confining_stress", float(confining_stress or 0.0)),
                         ("max_strain", float(max_strain))))
    return in_precision(Setup(state, params, frame, plan), precision)


# ----------------------------------------------------------------------------- the tests
def derive_box(raw, frame, plan):
    """:func:`derive` of a box-shaped specimen (UCS, biaxial, triaxial)."""
    return derive(raw, frame, plan, box_volume)


def _make(name, derive_fn, doc, confined, disc=False):
    def setup(specimens, params, **options):
        options["disc"] = disc
        if confined and options.get("confining_stress") is None:
            raise InputError(f"the {name} test needs confining_stress [Pa]")
        if not confined and options.get("confining_stress") is not None:
            raise InputError(f"the {name} test has free sides: use jdem.lab.BIAXIAL for "
                             f"confining_stress = {options['confining_stress']!r}")
        return platen_setup(test, specimens, params, **options)

    setup.__doc__ = doc
    setup.__name__ = name
    test = LabTest(name, setup, load, boundary, observe, derive_fn)
    return test


_COMMON = """
    specimens        a :class:`jdem.specimen.Specimen` (or ``(particles, bonds[, info])``),
                     or a list of them: an ensemble of packings run as one batch
    params           e.g. :func:`jdem.materials.rock_params` (rock 0, platen 1); a
                     leading member axis runs a sweep; its damping and time step
                     are replaced by those of the set-up
    max_strain       axial strain reached at the end of the loading
    loading_rate     platen speed / bar wave speed sqrt(E / rho) (default
                     ``DEFAULT_LOADING_RATE``, quasi-static: see :func:`jdem.lab.certify`)
    platen_step      instead of ``loading_rate``: platen displacement per step [m]
                     (one per member allowed)
    damping          :func:`jdem.lab.smooth` (default) or :func:`jdem.lab.local`
    record_every     steps per record (default: about 200 records of loading)
    ramp_transits    wave transits over which the platen speeds up
    top_stress       UCS only: hold the top platen at this compressive stress [Pa]
                     (servo, 000 eq 4-69) instead of driving it
    dt               time step [s] (default: ``timestep.recommended`` of the
                     critical step with the platens touching, for stiffnesses
                     ``stiffness_margin`` times those of ``params``, so that a
                     calibration may raise E that far)
    bond_section     2D bending section of the bonds: "circular" (default, 002
                     eq 5 as the seed) or "slab" (unit thickness), see
                     :class:`jdem.state.Config`
    precision        "float32" (default: within 0.5 % of float64, tests/
                     test_precision.py) or "float64" (:mod:`jdem.precision`)
"""

UCS = _make("ucs", derive_box, """Uniaxial compression (002 §2): fixed bottom
    platen, top platen driven down, free sides.  Returns a :class:`Setup`.
""" + _COMMON, False)

BIAXIAL = _make("biaxial", derive_box, """Biaxial (2D) / triaxial (3D)
    compression: lateral walls servo-controlled to ``confining_stress`` [Pa]
    (000 eq 4-69) after an isotropic preload of ``preload_transits`` wave
    transits.  Returns a :class:`Setup`.
""" + _COMMON, True)

BRAZILIAN = _make("brazilian", derive_brazilian, """Brazilian splitting
    test: diametral compression of a 2D disc (:func:`jdem.specimen.generate`
    ``("disc", D, ...)``) between flat rigid platens.  ``axial_stress`` is the
    load per metre of thickness; ``tensile_strength_indirect`` = 2P / (pi D t).
""" + _COMMON, False, disc=True)

TRIAXIAL = BIAXIAL   #: the same test; in 3D the lateral walls confine two axes
