"""The strain-energy ratio lambda = L_p / L_e of 002 §1.4 (eq 15-17): a bonded 2D
block at rest under a uniaxial stress, its bond strain energy against that of
an elastic continuum of the same size, E and nu.  Damping: as given (the seed
study used local damping 0.8, :func:`jdem.lab.local`).
Citations ("002 eq 16") refer to the documents listed in REFERENCES.md."""
from __future__ import annotations

import numpy as np

from jdem.lab import damping as damping_mod
from jdem.lab.core import run as run_test
from jdem.lab.pattern import bond_points
from jdem.lab.platen import UCS
from jdem.materials import ROCK, rock_bond_value
from jdem.specimen import as_arrays
from jdem.validate import InputError

def continuum_strain_energy(stress, E, nu, volume, plane="strain"):
    """Strain energy of an elastic block under uniaxial stress ``stress`` with free
    sides, L_e = sigma^2 / (2 E') V (002 eq 16): plane stress E' = E, plane strain
    E' = E / (1 - nu^2) (the out-of-plane strain held at zero)."""
    if plane not in ("strain", "stress"):
        raise InputError(f"plane must be 'strain' or 'stress', got {plane!r}")
    e_eff = E if plane == "stress" else E / (1.0 - nu ** 2)
    return stress ** 2 / (2.0 * e_eff) * volume


def coordination_energy_ratio(specimen, params, *, stress=1e6, plane="strain",
                              record_every=50, chunk_steps=2000, max_steps=200_000,
                              min_steps=10_000, tol=2e-3, dt=None, core_margin=0.2,
                              damping=None, bond_section="circular", progress=False):
    """lambda = L_p / L_e of 002 §1.4 (eq 15-16) for one bonded 2D block.

    The block sits between a fixed bottom platen and a top platen servo-controlled
    to ``stress`` (000 eq 4-69, compressive, area = block width x 1 m); the sides
    are free.  The run goes on in chunks until it is at rest: the top and bottom
    platen stresses within ``tol`` of ``stress`` and the kinetic energy below
    ``tol`` x the bond energy (at least ``min_steps``, at most ``max_steps``).

    L_p is the bond strain energy (002 eq 16, normal + shear, as
    :func:`jdem.bond.bond_strain_energy`) of the rock's bonds (both particles of
    material 0); with bonded loading plates (:func:`jdem.specimen.add_plates`)
    the plates' bonds and their bonds to the rock are left out, as the seed's
    finite-element plates are, and reported as ``L_p_loading``.  L_e is the energy of a continuum block of the
    same size and E, nu under the same uniaxial stress (002 eq 16), by default in
    plane strain: the seed's finite-element value, 0.151 J for 10 cm x 10 cm,
    E = 30 GPa, nu = 0.3, 1 MPa, is the plane-strain figure (1 - nu^2) sigma^2 V
    / (2E) = 0.1517 J (plane stress would give 0.1667 J).  V = width x height x
    1 m of the specimen box.

    ``bond_section`` is the 2D bending section (:class:`jdem.state.Config`).

    Boundary effect: a random packing touches a flat platen at a few particles
    only, and the "seating" of the others takes a displacement comparable to the
    whole elastic one at 1 MPa on a small block; the bonds near the platens then
    store extra energy.  Steel plates bonded to the faces
    (:func:`jdem.specimen.add_plates`, as the seed's plates of 002 Fig 7) load
    every boundary particle and take that out.  ``lam_core`` = L_p / L_e over
    the bulk only: the bonds whose contact point lies farther than
    ``core_margin`` x H from both faces of the specimen box, against
    sigma^2 / (2 E') times that slab's volume.

    Returns a dict: ``lam``, ``L_p``, ``L_e``, ``L_p_loading``, ``lam_core``, ``L_p_core``,
    ``L_e_core``, ``coordination`` (N-bar of the
    specimen), ``n_particles``, ``n_bonds``, ``steps``, ``top_stress``,
    ``bottom_stress``, ``avg_stress`` (d, d) (averaged stress tensor with the
    current volume), ``axial_strain`` (platen displacement / platen distance h0),
    ``E_macro`` = stress H / (platen displacement), H the height of the specimen
    box (with loading plates: the rock's height; the plates' own shortening,
    2 x 2 rows of steel discs, is counted as the rock's),
    ``kinetic_energy``, ``contact_energy``, ``converged`` and the ``history``.
    """
    particles, bonds, info = as_arrays(specimen)
    damping = damping_mod.local(0.8) if damping is None else damping
    if np.ndim(params.dt) != 0:
        raise InputError("coordination_energy_ratio takes unbatched params")
    su = UCS.setup(specimen, params, top_stress=stress, platen_step=1e-12, max_strain=1e-9,
                   record_every=record_every, dt=dt, damping=damping, bond_section=bond_section)
    n_chunk = max(1, chunk_steps // record_every)
    su = su.replace(plan=su.plan.replace(n_records=n_chunk, ramp_records=1))
    parts = []
    steps = 0
    converged = False
    while steps < max_steps:
        res = run_test(su, progress=False, check_dt=steps == 0, warn_dynamic=False)
        su = res.setup
        hist = {k: v for k, v in res.history.items() if not k.startswith("end_")}
        parts.append(hist)
        steps += n_chunk * record_every
        state = res.state
        top, bot = float(hist["axial_stress"][-1]), float(hist["bottom_stress"][-1])
        ke, be = float(hist["kinetic_energy"][-1]), float(hist["bond_energy"][-1])
        if progress:
            print(f"  energy ratio: {steps} steps, top {top / 1e6:.4f} MPa, bottom "
                  f"{bot / 1e6:.4f} MPa, KE / L_p {ke / max(be, 1e-300):.2e}")
        if (steps >= min_steps and abs(top / stress - 1) < tol and abs(bot / stress - 1) < tol
                and ke < tol * be):
            converged = True
            break
    config = su.plan.config
    dim = int(particles.pos.shape[1])
    h0 = float(su.frame.h0)
    w0 = np.asarray(su.frame.w0)
    history = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    lo, hi = specimen.box if hasattr(specimen, "box") else (None, None)
    if lo is not None:
        volume = float(np.prod(np.asarray(hi) - np.asarray(lo)))
    else:
        volume = h0 * float(np.prod(w0))
    l_e = continuum_strain_energy(stress, float(rock_bond_value(su.params, "bond_youngs")),
                                  float(rock_bond_value(su.params, "bond_poisson")), volume,
                                  plane)
    # the bulk: bonds whose contact point lies farther than core_margin x H from
    # either platen, against the continuum energy of that slab
    point, _, _ = bond_points(state)
    b = state.bonds
    e_bond = 0.5 * (-np.asarray(b.normal_force) * np.asarray(b.u_n)
                    - np.sum(np.asarray(b.shear_force) * np.asarray(b.u_s), axis=-1))
    live = np.asarray(b.valid) & ~np.asarray(b.broken)
    # the rock's bonds only: loading plates (jdem.specimen.add_plates, material
    # != ROCK) and their bonds to the rock are the loading device, as the seed's
    # finite-element plates are
    mat = np.asarray(state.particles.material)
    rock = (mat[np.asarray(b.i)] == ROCK) & (mat[np.asarray(b.j)] == ROCK)
    l_p = float(np.sum(np.where(live & rock, e_bond, 0.0)))
    l_p_loading = float(np.sum(np.where(live & ~rock, e_bond, 0.0)))
    ax = dim - 1
    if lo is not None:    # the rock's faces (the platens when there are no plates)
        wpos = np.array([float(lo[ax]), float(hi[ax])])
    else:
        wpos = np.asarray(state.walls.point)[:2, ax]
    height = float(wpos[1] - wpos[0])
    margin = core_margin * height
    core = live & rock & (point[:, ax] > wpos[0] + margin) & (point[:, ax] < wpos[1] - margin)
    l_p_core = float(np.sum(np.where(core, e_bond, 0.0)))
    l_e_core = l_e * (height - 2 * margin) / height
    n_b = int(np.sum(np.asarray(bonds.valid)))
    n_p = int(np.sum(np.asarray(particles.valid)))
    coord = getattr(specimen, "coordination", None)
    return dict(lam=l_p / l_e, L_p=l_p, L_e=l_e, L_p_loading=l_p_loading,
                lam_core=l_p_core / l_e_core,
                L_p_core=l_p_core, L_e_core=l_e_core,
                coordination=float(coord) if coord is not None else 2.0 * n_b / n_p,
                n_particles=n_p, n_bonds=n_b, steps=steps, top_stress=top, bottom_stress=bot,
                avg_stress=history["avg_stress"][-1], axial_strain=float(history["axial_strain"][-1]),
                E_macro=stress * height / (float(history["axial_strain"][-1]) * h0),
                kinetic_energy=ke, contact_energy=float(history["contact_energy"][-1]),
                converged=converged, history=history, state=state, config=config)
