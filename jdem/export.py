"""Export to ParaView: particles and bonds as VTK unstructured grids.

One ``.vtu`` file per record and a ``.pvd`` collection that gives each its time
(File > Open the ``.pvd``; ParaView then plays the records as a time series).
Files are written with meshio (a well-kept reader and writer of mesh formats,
pure Python on NumPy, which reads the files back too; its VTU writer is the
XML format ParaView and VisIt open directly), so that the same library checks
them in the tests.

Each file holds the valid particles as ``vertex`` cells and the valid bonds as
``line`` cells between the two particle centres:

point data (particles)  ``radius`` [m], ``velocity`` (3,) [m/s], ``spin`` (3,)
                        [rad/s] (2D: about z), ``material``, ``damage`` (broken
                        bonds / bonds of the particle, 0 without bonds)
cell data               ``broken`` (0 / 1), ``break_mode`` (0 intact, 1 tension,
                        2 shear), ``normal_force`` [N] (compression positive);
                        on the vertex cells 0 (they are not bonds)

2D positions get z = 0.  In ParaView, a Glyph filter (sphere, scale by
``radius``, scale factor 2) shows the particles; colouring the lines by
``break_mode`` with a threshold on ``broken`` shows the cracks.
"""
from __future__ import annotations

import pathlib
from xml.sax.saxutils import quoteattr

import numpy as np

from jdem.validate import InputError

FRAME_KEYS = ("pos", "vel", "angvel", "bond_broken", "bond_mode", "bond_normal_force")


def _xyz(a, n):
    """(n, 3) from (n, 2) / (n, 3) vectors or (n,) z-components (2D spin)."""
    a = np.asarray(a, np.float64)
    if a.ndim == 1:
        return np.stack([np.zeros(n), np.zeros(n), a], axis=1)
    return a if a.shape[1] == 3 else np.concatenate([a, np.zeros((n, 1))], axis=1)


def particle_mesh(particles, bonds, *, pos=None, vel=None, angvel=None, broken=None,
                  break_mode=None, normal_force=None):
    """A ``meshio.Mesh`` of the valid particles (vertex cells) and valid bonds
    (line cells) with the data of the module docstring.  ``pos`` (N, d),
    ``vel``, ``angvel``, ``broken`` (B,), ``break_mode`` (B,) and
    ``normal_force`` (B,) replace the arrays of ``particles`` / ``bonds``
    (e.g. one record of a history); unbatched arrays only."""
    import meshio

    if np.ndim(particles.pos) != 2:
        raise InputError("particle_mesh takes one (unbatched) state; pick a member first")
    valid = np.asarray(particles.valid, bool)
    rows = np.nonzero(valid)[0]
    new_index = np.cumsum(valid) - 1
    n = rows.size
    pos = np.asarray(particles.pos if pos is None else pos)[rows]
    vel = np.asarray(particles.vel if vel is None else vel)[rows]
    angvel = np.asarray(particles.angvel if angvel is None else angvel)[rows]
    bi, bj = np.asarray(bonds.i), np.asarray(bonds.j)
    bv = np.asarray(bonds.valid, bool) & valid[bi] & valid[bj]
    sel = np.nonzero(bv)[0]
    broken = np.asarray(bonds.broken if broken is None else broken, bool)[sel]
    mode = np.where(broken, np.asarray(bonds.break_mode if break_mode is None else break_mode)[sel],
                    0).astype(np.int32)
    fn = np.asarray(bonds.normal_force if normal_force is None else normal_force,
                    np.float64)[sel]
    lines = np.stack([new_index[bi[sel]], new_index[bj[sel]]], axis=1).astype(np.int64)
    count = np.bincount(lines.ravel(), minlength=n).astype(np.float64)
    n_broken = np.bincount(lines[broken].ravel(), minlength=n).astype(np.float64)
    damage = np.where(count > 0, n_broken / np.where(count > 0, count, 1.0), 0.0)
    point_data = dict(radius=np.asarray(particles.radius, np.float64)[rows],
                      velocity=_xyz(vel, n), spin=_xyz(angvel, n),
                      material=np.asarray(particles.material, np.int32)[rows], damage=damage)
    cells = [("vertex", np.arange(n, dtype=np.int64)[:, None])]
    zero_v = lambda dt: np.zeros(n, dt)
    cell_data = dict(broken=[zero_v(np.int32)], break_mode=[zero_v(np.int32)],
                     normal_force=[zero_v(np.float64)])
    if sel.size:
        cells.append(("line", lines))
        cell_data["broken"].append(broken.astype(np.int32))
        cell_data["break_mode"].append(mode)
        cell_data["normal_force"].append(fn)
    return meshio.Mesh(_xyz(pos, n), cells, point_data=point_data, cell_data=cell_data)


def write_vtk(path, state):
    """Write one (unbatched) :class:`jdem.State` as a ``.vtu`` file; returns the path."""
    import meshio

    path = pathlib.Path(path)
    if path.suffix != ".vtu":
        raise InputError(f"write_vtk writes .vtu files, got {str(path)!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.write(path, particle_mesh(state.particles, state.bonds), file_format="vtu")
    return path


def frame_observables(state, params, config):
    """:func:`jdem.measure.basic_observables` plus what :func:`write_series` draws
    per record: ``pos``, ``vel``, ``angvel`` (N, ...), ``bond_broken``,
    ``bond_mode``, ``bond_normal_force`` (B,).  Pass it as ``observe`` to
    :func:`jdem.simulate.run`; each record then costs (N (2d + 1) + 3 B) numbers."""
    from jdem.measure import basic_observables

    p, b = state.particles, state.bonds
    return dict(basic_observables(state, params, config), pos=p.pos, vel=p.vel,
                angvel=p.angvel, bond_broken=b.broken, bond_mode=b.break_mode,
                bond_normal_force=b.normal_force)


def write_series(directory, state, history, *, name="frame", every=1):
    """Write every ``every``-th record of ``history`` as ``<name>_0000.vtu``, …
    under ``directory`` and the collection ``<name>.pvd`` (record times from
    ``history["time"]``, else ``history["step"]``); returns the ``.pvd`` path.

    ``state`` (unbatched) gives what does not change (radii, materials, which
    rows are particles and bonds) and the arrays ``history`` lacks.  A history
    recorded with ``observe=`` :func:`frame_observables` gives the motion and
    the bonds' state per record.  A history without them (e.g. a lab test's,
    which records ``step``) shows the final positions, and a bond as broken from
    the record whose step reaches its ``break_step``: the failure pattern as it
    develops."""
    import meshio

    history = {k: np.asarray(v) for k, v in history.items()}
    if "time" in history:
        times = history["time"]
    elif "step" in history:
        times = history["step"].astype(np.float64)
    else:
        raise InputError("history needs a 'time' or a 'step' entry to order its records")
    if times.ndim != 1:
        raise InputError(f"write_series takes one member's history, got 'time'/'step' of shape "
                         f"{times.shape}")
    every = int(every)
    if every < 1:
        raise InputError(f"every must be a positive integer, got {every!r}")
    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    b = state.bonds
    break_step = np.asarray(b.break_step)
    entries = []
    for k in range(0, times.size, every):
        rec = {key: history[key][k] for key in FRAME_KEYS if key in history}
        if "bond_broken" not in rec and "step" in history:
            rec["bond_broken"] = (break_step >= 0) & (break_step <= history["step"][k])
        mesh = particle_mesh(state.particles, b, pos=rec.get("pos"), vel=rec.get("vel"),
                             angvel=rec.get("angvel"), broken=rec.get("bond_broken"),
                             break_mode=rec.get("bond_mode"),
                             normal_force=rec.get("bond_normal_force"))
        file = directory / f"{name}_{k:04d}.vtu"
        meshio.write(file, mesh, file_format="vtu")
        entries.append((float(times[k]), file.name))
    pvd = directory / f"{name}.pvd"
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(f)}/>'
              for t, f in entries]
    lines += ["  </Collection>", "</VTKFile>", ""]
    tmp = pvd.with_suffix(".pvd.tmp")
    tmp.write_text("\n".join(lines))
    tmp.replace(pvd)
    return pvd
