"""Named material parameters and presets.

* :data:`PARAMETERS`, :func:`material`, :func:`values_of` -- the names a user fits
  or sweeps (``E``, ``nu``, ``T0``, ``c0``, ``phi``, ``eps_lim``, ``gamma_lim``
  and the tied pairs ``strength`` and ``kappa``) and how they set ``Params``.
* :func:`rock_params` -- a bonded rock (material ``ROCK`` = 0) and a rigid-ish
  platen (material ``PLATEN`` = 1), the set-up of 002 §2.
* :func:`seed_params` -- the bond values of the single-bond tests of 002 §1.3.

Units: SI (Pa, rad, m).  Citations: see REFERENCES.md.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jdem.batch import broadcast_batch
from jdem.state import Params, make_params
from jdem.validate import InputError, check_params

ROCK = 0     #: material index of the rock particles
PLATEN = 1   #: material index of platens, lateral walls and bonded loading plates
PLATE_STRENGTH = 1e12   #: bond strengths [Pa] of a loading plate (it never yields)

#: name -> the Params fields it sets
PARAMETERS = {
    "E": ("bond_youngs",),
    "nu": ("bond_poisson",),
    "T0": ("bond_tensile",),
    "c0": ("bond_cohesion",),
    "phi": ("bond_friction_angle",),
    "eps_lim": ("bond_tensile_strain",),
    "gamma_lim": ("bond_shear_strain",),
    "strength": ("bond_tensile", "bond_cohesion"),
    "kappa": ("bond_tensile_strain", "bond_shear_strain"),
}


def check_names(names):
    """Raise ``InputError`` for a name that is not in :data:`PARAMETERS`."""
    for n in names:
        if n not in PARAMETERS:
            raise InputError(f"unknown parameter {n!r}; choose from {sorted(PARAMETERS)}")


def per_material_bonds(params: Params) -> bool:
    """True if the ``bond_*`` fields of ``params`` hold one value per material
    (their shape is that of ``dt`` plus a material axis)."""
    return np.ndim(params.bond_youngs) > np.ndim(params.dt)


def rock_bond_value(params: Params, field: str):
    """The value of the bond field ``field`` for the rock (material :data:`ROCK`):
    the field itself when it holds one value for all bonds, else its rock entry
    (batch axes kept)."""
    value = getattr(params, field)
    return value[..., ROCK] if per_material_bonds(params) else value


def material(params: Params, values: dict) -> Params:
    """``params`` with the named values set (:data:`PARAMETERS`); traceable.
    With per-material bond fields the named values set the rock's (material 0)
    entries; the other materials keep theirs.

    When ``E`` or ``nu`` change, the rock contacts (material 0) follow as in
    :func:`rock_params`: kn scales with E, ks = kn / (2 (1 + nu)).
    """
    check_names(values)
    new = {}
    for name, v in values.items():
        for field in PARAMETERS[name]:
            old = jnp.asarray(getattr(params, field))
            v = jnp.asarray(v, old.dtype)
            if per_material_bonds(params):
                shape = jnp.broadcast_shapes(old.shape[:-1], v.shape) + old.shape[-1:]
                new[field] = jnp.broadcast_to(old, shape).at[..., ROCK].set(v)
            else:
                new[field] = v
    out = params._replace(**new)
    if "E" in values or "nu" in values:
        kn0 = (params.kn[..., 0] * rock_bond_value(out, "bond_youngs")
               / rock_bond_value(params, "bond_youngs"))
        ks0 = kn0 / (2.0 * (1.0 + rock_bond_value(out, "bond_poisson")))
        out = out._replace(kn=out.kn.at[..., 0].set(kn0), ks=out.ks.at[..., 0].set(ks0))
    return out


def values_of(params: Params, names) -> dict:
    """The named values of ``params`` (first field of each name; the rock's with
    per-material bond fields) as floats."""
    check_names(names)
    return {n: float(np.asarray(rock_bond_value(params, PARAMETERS[n][0]))) for n in names}


def rock_params(dim: int = 2, *, E=30e9, nu=0.22, T0=3e6, c0=3e6, phi_deg=30.0, kappa=1e-3,
                local_damping=0.8, radius=None, friction=None, platen_stiffness=10.0,
                platen_friction=0.0, plate_youngs=None, plate_poisson=0.3, dt=1e-8,
                **kw) -> Params:
    """``Params`` of a bonded rock (material 0) and a platen (material 1, 002 §2).

    E, nu         Young's modulus [Pa] and Poisson ratio of the linked bars (002 eq 2)
    T0, c0        initial tensile strength and cohesion [Pa] (002 eq 6, 8)
    phi_deg       internal friction angle [deg] of the bonds (002 eq 8); the
                  unbonded rock contacts get ``friction = tan(phi)`` unless given
    kappa         fracture strain: ``bond_tensile_strain = bond_shear_strain = kappa``
                  (002 §2.1).  A sequence gives a *batched* ``Params`` (leading
                  axis, one member per value) for a vmapped sweep
    local_damping local non-viscous damping (000 eq 3-19), 0.8 in 002 §2.1; the
                  lab tests replace the damping by the one they are told to use
                  (:mod:`jdem.lab.damping`)
    radius        3D only: the particle radius R [m] of the contact stiffness below

    Unbonded contact stiffness, consistent with a bond between equal particles
    (002 eq 1-2): 2D ``kn = E A_c / L = E 2R / 2R = E`` [N/m per m of thickness];
    3D ``kn = E pi R^2 / 2R = E pi R / 2``; ``ks = kn G / E`` with
    ``G = E / (2 (1 + nu))``.  The platen (material 1) is ``platen_stiffness``
    times stiffer (linear model; the pair stiffness is the harmonic mean, 000
    eq 4-9, so a particle-platen contact has about 2 kn) and frictionless by
    default (``platen_friction = 0``: "normal constraint" of the platens, 002
    §2.1; the smaller friction coefficient of a pair is used).  ``dt`` is a
    placeholder: the lab tests replace it by ``jdem.timestep.recommended``.

    plate_youngs  None (default): one set of bond values for all bonds.  A modulus
                  [Pa] (steel: 200e9) makes the bond fields per material: material
                  1 gets E = ``plate_youngs``, nu = ``plate_poisson`` and strengths
                  of :data:`PLATE_STRENGTH` (it never yields), for the bonded
                  loading plates of :func:`jdem.specimen.add_plates` (002 Fig 7)
    Further keywords go to :func:`jdem.state.make_params`.
    """
    if dim not in (2, 3):
        raise InputError(f"dim must be 2 or 3, got {dim!r}")
    g_over_e = 1.0 / (2.0 * (1.0 + float(nu)))
    if dim == 2:
        kn = float(E)
    else:
        if radius is None:
            raise InputError("rock_params(dim=3) needs radius (the particle radius R of "
                             "kn = E pi R / 2)")
        kn = float(E) * np.pi * float(radius) / 2.0
    mu = float(np.tan(np.deg2rad(phi_deg))) if friction is None else float(friction)
    kappas = np.atleast_1d(np.asarray(kappa, dtype=np.float64))
    phi = float(np.deg2rad(phi_deg))
    bond = dict(bond_youngs=E, bond_poisson=nu, bond_tensile=T0, bond_cohesion=c0,
                bond_friction_angle=phi, bond_tensile_strain=float(kappas[0]),
                bond_shear_strain=float(kappas[0]))
    if plate_youngs is not None:   # material 1: a steel plate that never yields
        plate = dict(bond_youngs=plate_youngs, bond_poisson=plate_poisson,
                     bond_tensile=PLATE_STRENGTH, bond_cohesion=PLATE_STRENGTH,
                     bond_friction_angle=phi, bond_tensile_strain=1.0, bond_shear_strain=1.0)
        bond = {k: [float(v), float(plate[k])] for k, v in bond.items()}
    base = make_params(dim=dim, n_materials=2, dt=dt, kn=[kn, platen_stiffness * kn],
                       ks=[kn * g_over_e, platen_stiffness * kn * g_over_e],
                       friction=[mu, platen_friction], youngs=[E, platen_stiffness * E],
                       poisson=[nu, nu], local_damping=local_damping, **bond, **kw)
    if np.ndim(kappa) == 0:
        return base
    params = broadcast_batch(base, kappas.size)
    k = jnp.asarray(kappas, dtype=jnp.asarray(base.dt).dtype)
    params = material(params, {"kappa": k})
    check_params(params)
    return jax.tree_util.tree_map(lambda a: jnp.array(a), params)  # own the memory


#: Seed values of 002 §1.3 (single linked bar).
SEED_PARAMS = dict(bond_youngs=10e9, bond_poisson=0.22, bond_tensile=3e6, bond_cohesion=3e6,
                   bond_friction_angle=float(np.deg2rad(30.0)), bond_tensile_strain=1e-3,
                   bond_shear_strain=3e-3)
#: local damping of the single-bond tests (002 §1.3) and of 002 §2.1
SEED_LOCAL_DAMPING = 0.8


def seed_params(dim: int = 3, **overrides) -> Params:
    """``Params`` with the 002 §1.3 bond values (E = 10 GPa, nu = 0.22,
    T0 = c0 = 3 MPa, phi = 30 deg, eps_lim = 0.1 %, gamma_lim = 0.3 %) and local
    damping 0.8; ``dt`` is a placeholder that the single-bond set-up replaces."""
    kw = dict(SEED_PARAMS, local_damping=SEED_LOCAL_DAMPING)
    kw.update(overrides)
    return make_params(dim=dim, **kw)
