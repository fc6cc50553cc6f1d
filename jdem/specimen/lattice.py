"""Regular lattices of equal discs / spheres, bonded between touching neighbours.

Kinds (touching neighbours per interior particle in brackets):

* ``"square"`` (4) and ``"triangular"`` (6; the hexagonal close packing of
  discs, also accepted as ``"hexagonal"``) in 2D;
* ``"simple_cubic"`` (6) and ``"fcc"`` (12, face-centred cubic) in 3D.

``counts`` are the number of particles along each axis for the square,
triangular and simple cubic lattices (odd rows of the triangular lattice are
shifted by half a spacing, rows are sqrt(3)/2 spacings apart), and the number of
cubic cells of edge sqrt(2) x spacing along each axis for fcc (4 particles per
cell).  Sites are ordered row by row (x fastest, then y, then z).

The elastic constants of a bonded triangular lattice of normal / shear bond
stiffness k_n, k_s [N/m per m of thickness] follow from 000 eq 4-44 with the
affine displacement (each site is a centre of symmetry, so the affine field is
in equilibrium and the particles do not spin): lambda = sqrt(3)/4 (k_n - k_s),
mu = sqrt(3)/4 (k_n + k_s), hence the 2D Young's modulus
E = 2 sqrt(3) k_n (k_n + k_s) / (3 k_n + k_s) and Poisson's ratio
nu = (k_n - k_s) / (3 k_n + k_s) (:func:`triangular_elastic_constants`).
Citations refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import math

import numpy as np

from jdem.bond import create_bonds
from jdem.specimen.container import Specimen, particle_volume
from jdem.state import make_particles
from jdem.validate import InputError, require_positive

LATTICES = {"square": 2, "triangular": 2, "hexagonal": 2, "simple_cubic": 3, "fcc": 3}
_FCC_BASIS = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5]])


def _check_kind(kind, counts):
    if kind not in LATTICES:
        raise InputError(f"kind must be one of {sorted(LATTICES)}, got {kind!r}")
    dim = LATTICES[kind]
    counts = tuple(counts) if np.ndim(counts) else (counts,)
    if len(counts) != dim:
        raise InputError(f"counts must hold {dim} numbers for a {kind} lattice, got {counts!r}")
    for v in counts:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"counts must be positive integers, got {counts!r}")
    return dim, tuple(int(v) for v in counts)


def lattice_sites(kind, counts, spacing):
    """Sites (n, d) [m] of a lattice of nearest-neighbour distance ``spacing``,
    the first site at the origin; see the module docstring for ``counts``."""
    dim, counts = _check_kind(kind, counts)
    s = float(require_positive("spacing", spacing))
    if kind == "fcc":
        a = s * np.sqrt(2)  # cubic cell edge; nearest neighbours at a / sqrt 2
        nx, ny, nz = counts
        cells = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"),
                         -1).reshape(-1, 1, 3)
        pts = ((cells + _FCC_BASIS[None]) * a).reshape(-1, 3)
        return pts[np.lexsort((pts[:, 0], pts[:, 1], pts[:, 2]))]
    grids = np.meshgrid(*[np.arange(c) for c in counts[::-1]], indexing="ij")[::-1]
    idx = np.stack([g.ravel() for g in grids], axis=1).astype(np.float64)  # x fastest
    if kind in ("triangular", "hexagonal"):
        x = (idx[:, 0] + 0.5 * (idx[:, 1] % 2)) * s
        y = idx[:, 1] * s * np.sqrt(3) / 2
        return np.stack([x, y], axis=1)
    return idx * s


def lattice_packing(kind, counts, radius, *, origin=None):
    """Centres (n, d) [m] and radii (n,) [m] of touching equal particles on a
    lattice (spacing 2 ``radius``), the lower corner of their bounding box at
    ``origin`` (default the origin)."""
    dim = LATTICES.get(kind, 2)
    r = float(require_positive("radius", radius))
    pos = lattice_sites(kind, counts, 2.0 * r) + r
    if origin is not None:
        o = np.asarray(origin, np.float64)
        if o.shape != (dim,) or not np.all(np.isfinite(o)):
            raise InputError(f"origin must be {dim} finite numbers, got {origin!r}")
        pos = pos + o
    return pos, np.full(pos.shape[0], r)


def bond_touching(particles, *, gap_tolerance=None):
    """Bonds (:func:`jdem.bond.create_bonds`) between every pair of valid
    particles whose gap is at most ``gap_tolerance`` [m] (default 1e-6 x the
    smallest radius: the touching neighbours of a lattice)."""
    rad = np.asarray(particles.radius)[np.asarray(particles.valid)]
    g = 1e-6 * float(np.min(rad)) if gap_tolerance is None else float(gap_tolerance)
    return create_bonds(particles, particles.pos.shape[1], gap_tolerance=g)


def bonded_lattice(kind, counts, radius, *, density=2500.0, origin=None, dtype=None) -> Specimen:
    """A :class:`jdem.specimen.Specimen` of touching equal particles on a lattice,
    every touching pair bonded, usable wherever a generated specimen is.

    ``density`` [kg/m^3] is the particles' material density.  ``box`` is the
    bounding box of the particles; ``porosity`` is measured in it (square 1 - pi/4,
    triangular 1 - pi/(2 sqrt 3) for large counts); ``coordination`` is
    2 n_bonds / n.  ``info`` holds ``lattice``, ``counts``, ``spacing`` [m] and
    ``n_particles``, ``n_bonds``, ``r_min``, ``r_max``, ``r_mean``.
    """
    pos, rad = lattice_packing(kind, counts, radius, origin=origin)
    particles = make_particles(pos, rad, density=density, dtype=dtype)
    bonds = bond_touching(particles)
    lo = (pos - rad[:, None]).min(axis=0)
    hi = (pos + rad[:, None]).max(axis=0)
    dim = pos.shape[1]
    porosity = 1.0 - float(np.sum(particle_volume(rad, dim))) / float(np.prod(hi - lo))
    n_bonds = int(np.sum(np.asarray(bonds.valid)))
    r = float(rad[0])
    info = dict(lattice=kind, counts=tuple(int(c) for c in np.atleast_1d(counts)),
                spacing=2.0 * r, n_particles=int(rad.size), n_bonds=n_bonds,
                r_min=r, r_max=r, r_mean=r, shape="lattice")
    return Specimen(particles=particles, bonds=bonds, box=(lo, hi), porosity=porosity,
                    coordination=2.0 * n_bonds / rad.size, seed=0, info=info)


def triangular_elastic_constants(kn, ks):
    """Plane elastic constants of a bonded triangular lattice (module docstring).

    ``kn``, ``ks`` [N/m per m of thickness] the bond normal and shear
    stiffnesses.  Returns a dict with ``lame_lambda``, ``shear_modulus``,
    ``youngs`` [Pa] and ``poisson`` (2D: E = 4 mu (lambda + mu) / (lambda + 2 mu),
    nu = lambda / (lambda + 2 mu))."""
    kn = float(require_positive("kn", kn))
    ks = float(require_positive("ks", ks, allow_zero=True))
    c = math.sqrt(3.0) / 4.0
    lam, mu = c * (kn - ks), c * (kn + ks)
    return dict(lame_lambda=lam, shear_modulus=mu,
                youngs=4.0 * mu * (lam + mu) / (lam + 2.0 * mu), poisson=lam / (lam + 2.0 * mu))

