"""Input checks that turn bad input into errors naming the field and the value.

These run on the host (NumPy), before anything is traced, so they never slow a
jitted step.  Inside traced code use ``jnp.where`` instead.

Where each check runs:

* :func:`check_particle_input` -- :func:`jdem.state.make_particles`;
* :func:`check_params` -- :func:`jdem.state.make_params` and the host loop;
* :func:`check_config` -- ``jdem.state.Config`` on construction;
* :func:`check_particles` -- :func:`jdem.simulate.make_state` (particles built
  by hand or by ``_replace`` do not pass through ``make_particles``);
* :func:`check_materials` -- the host loop :func:`jdem.simulate.run` and
  :func:`jdem.timestep.check_timestep`, where particles meet ``Params``;
* :func:`read_text_file` -- the target CSV (:func:`jdem.targets.load_target`)
  and the ``--config`` TOML of the CLI;
* the dashpots (``contact_damping``, ``bond_damping``, ``viscous_damping``) have
  no fixed upper bound: the critical time step of :mod:`jdem.timestep` includes
  them, and :func:`jdem.timestep.check_timestep` refuses a step above it.
"""
from __future__ import annotations

import pathlib

import numpy as np


class InputError(ValueError):
    """Bad user input; the message names the field and the offending value."""


def _first_bad(a, bad):
    idx = np.argwhere(bad)
    first = tuple(int(k) for k in idx[0]) if idx.size else ()
    value = a[first] if first else a
    return first, float(value)


def _at(where):
    return f"[{', '.join(map(str, where))}]" if where else ""


def require_finite(name, value):
    a = np.asarray(value, dtype=np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        where, v = _first_bad(a, bad)
        raise InputError(f"{name}{_at(where)} must be finite, got {v}")
    return a


def require_positive(name, value, allow_zero=False):
    a = require_finite(name, value)
    bad = a < 0 if allow_zero else a <= 0
    if bad.any():
        where, v = _first_bad(a, bad)
        cmp = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name}{_at(where)} must be {cmp}, got {v}")
    return a


def require_range(name, value, lo, hi, *, hi_open=False):
    """``lo <= value <= hi``, or ``lo <= value < hi`` with ``hi_open``."""
    a = require_finite(name, value)
    bad = (a < lo) | ((a >= hi) if hi_open else (a > hi))
    if bad.any():
        where, v = _first_bad(a, bad)
        close = ")" if hi_open else "]"
        raise InputError(f"{name}{_at(where)} must lie in [{lo}, {hi}{close}, got {v}")
    return a


def require_int(name, value, minimum):
    """An integer (Python or NumPy, not bool) of at least ``minimum``."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if not ok:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {value!r}")
    return int(value)


def require_shape(name, value, shape):
    """``np.shape(value) == shape`` (``None`` passes: the default is used)."""
    if value is None:
        return None
    s = np.shape(value)
    if s != tuple(shape):
        raise InputError(f"{name} must have shape {tuple(shape)}, got {s}")
    return value


def check_coincident(name, pos, valid=None):
    """No two (valid) rows of ``pos`` may be equal: two particles with coincident
    centres have no contact normal, so they exert no force on each other."""
    pos = np.asarray(pos)
    idx = np.arange(pos.shape[0]) if valid is None else np.flatnonzero(np.asarray(valid))
    if idx.size < 2:
        return
    p = pos[idx]
    order = np.lexsort(p.T[::-1])
    s = p[order]
    same = np.all(s[1:] == s[:-1], axis=1)
    if same.any():
        k = int(np.argmax(same))
        a, b = sorted((int(idx[order[k]]), int(idx[order[k + 1]])))
        at = tuple(float(v) for v in pos[b])
        raise InputError(
            f"{name}[{b}] = {at} coincides with {name}[{a}]: particles with coincident "
            f"centres (distance 0) exert no force on each other")


def _check_material_index(name, material, valid=None):
    m = np.asarray(material)
    if m.size and not np.issubdtype(m.dtype, np.integer):
        mf = require_finite(name, m)
        bad = mf != np.round(mf)
        if bad.any():
            where, v = _first_bad(mf, bad)
            raise InputError(f"{name}{_at(where)} must be an integer index, got {v}")
    bad = m < 0
    if valid is not None:
        bad = bad & np.asarray(valid, bool)
    if bad.any():
        where, v = _first_bad(m, bad)
        raise InputError(f"{name}{_at(where)} must be a material index >= 0, got {int(v)}")


def check_particle_input(pos, radius, density, *, vel=None, angvel=None, material=None,
                         fixed_vel=None, fixed_rot=None):
    """The arguments of :func:`jdem.state.make_particles` (``None``: default)."""
    pos = np.asarray(pos)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise InputError(f"pos must have shape (n, 2) or (n, 3), got {pos.shape}")
    n, dim = pos.shape
    if n == 0:
        raise InputError(f"pos must hold at least one particle, got shape {pos.shape}")
    radius = np.asarray(radius)
    if radius.shape != (n,):
        raise InputError(f"radius must have shape ({n},), got {radius.shape}")
    require_finite("pos", pos)
    require_positive("radius", radius)
    if np.ndim(density) != 0:
        require_shape("density", density, (n,))
    require_positive("density", density)
    rs = () if dim == 2 else (3,)
    require_shape("vel", vel, (n, dim))
    require_shape("angvel", angvel, (n,) + rs)
    require_shape("fixed_vel", fixed_vel, (n, dim))
    require_shape("fixed_rot", fixed_rot, (n,) + rs)
    require_shape("material", material, (n,))
    if vel is not None:
        require_finite("vel", vel)
    if angvel is not None:
        require_finite("angvel", angvel)
    if material is not None:
        _check_material_index("material", material)
    check_coincident("pos", pos)


def check_particles(particles):
    """A ``Particles`` about to become a state: at least one valid row, and no
    two valid rows at the same centre."""
    valid = np.asarray(particles.valid, bool)
    if not valid.any():
        raise InputError(f"particles must hold at least one valid particle, got "
                         f"{valid.sum()} of capacity {valid.size}")
    check_coincident("particles.pos", np.asarray(particles.pos), valid)


def n_materials(params):
    """Number of materials M of ``params`` (length of its per-material arrays)."""
    shape = np.shape(params.kn)
    return int(shape[-1]) if shape else 1


def check_materials(state, params):
    """Every material index of a valid particle or wall must be below the number
    of materials of ``params`` (a gather out of range would silently read another
    material's values)."""
    m = n_materials(params)
    for name, mat, valid in (("particles.material", state.particles.material,
                              state.particles.valid),
                             ("walls.material", state.walls.material, state.walls.valid)):
        mat = np.asarray(mat)
        if not mat.size:
            continue
        valid = np.asarray(valid, bool)
        _check_material_index(name, mat, valid)
        bad = valid & (mat >= m)
        if bad.any():
            where, v = _first_bad(mat, bad)
            raise InputError(
                f"{name}{_at(where)} = {int(v)} is out of range: params has {m} "
                f"material{'s' if m != 1 else ''} (indices 0 to {m - 1})")


def check_config(config, contact_models, friction_rules):
    """The fields of a :class:`jdem.state.Config`; ``contact_models``: the names
    of the contact laws; ``friction_rules``: the names of the friction mixing rules."""
    if config.dim not in (2, 3):
        raise InputError(f"Config.dim must be 2 or 3, got {config.dim!r}")
    if config.contact_model not in contact_models:
        raise InputError(
            f"Config.contact_model must be one of {tuple(contact_models)}, got {config.contact_model!r}")
    if len(config.grid_origin) != config.dim or len(config.grid_shape) != config.dim:
        raise InputError(
            f"Config.grid_origin / grid_shape need {config.dim} entries, got "
            f"{config.grid_origin!r} / {config.grid_shape!r}")
    for axis, cells in enumerate(config.grid_shape):
        require_int(f"Config.grid_shape[{axis}]", cells, 1)
    require_finite("Config.grid_origin", config.grid_origin)
    if int(config.max_per_cell) < 1:
        raise InputError(f"Config.max_per_cell must be >= 1, got {config.max_per_cell!r}")
    for name in ("skin", "cell_size"):
        v = float(getattr(config, name))
        if not np.isfinite(v) or v <= 0:
            raise InputError(f"Config.{name} must be a positive finite length, got {v!r}")
    from jdem.state import BOND_SECTIONS

    if config.bond_section not in BOND_SECTIONS:
        raise InputError(f"Config.bond_section must be one of {BOND_SECTIONS}, "
                         f"got {config.bond_section!r}")
    if config.bond_section == "slab" and config.dim != 2:
        raise InputError("Config.bond_section = 'slab' is a 2D section; 3D bonds are circular "
                         f"(got dim = {config.dim})")
    rule = config.friction_mixing
    if isinstance(rule, str):
        if rule not in friction_rules:
            raise InputError(f"Config.friction_mixing must be one of {tuple(friction_rules)} "
                             f"or an M x M table, got {rule!r}")
    else:
        try:
            table = np.asarray(rule, dtype=np.float64)
        except (TypeError, ValueError):
            table = np.zeros((0,))
        if table.ndim != 2 or table.shape[0] != table.shape[1] or table.shape[0] < 1:
            raise InputError(f"Config.friction_mixing table must be square (M x M), got {rule!r}")
        if not np.all(np.isfinite(table)) or np.any(table < 0) or \
                not np.array_equal(table, table.T):
            raise InputError(f"Config.friction_mixing table must be symmetric, finite and "
                             f">= 0, got {rule!r}")


def check_params(params, dim=None):
    """Check every field of a :class:`jdem.state.Params` (host values only).

    ``dim``: the dimension ``gravity`` must have (its last axis, so a batched
    ``Params`` passes too).
    """
    import jax

    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(params)):
        return  # traced (inside jit / grad): checked where the values were made
    for name, value in params._asdict().items():
        require_finite(f"params.{name}", value)
    require_positive("params.dt", params.dt)
    for name in ("kn", "ks", "youngs", "bond_youngs"):
        require_positive(f"params.{name}", getattr(params, name))
    for name in ("friction", "contact_damping", "viscous_damping", "bond_tensile",
                 "bond_cohesion", "bond_tensile_strain", "bond_shear_strain",
                 "bond_damping"):
        require_positive(f"params.{name}", getattr(params, name), allow_zero=True)
    # 000 eq 3-19: F - alpha |F| sign(v) needs 0 <= alpha < 1 (with alpha = 1 no
    # force can push a moving particle further along its motion)
    require_range("params.local_damping", params.local_damping, 0.0, 1.0, hi_open=True)
    require_range("params.poisson", params.poisson, -1.0, 0.5)
    require_range("params.bond_poisson", params.bond_poisson, -1.0, 0.5)
    require_range("params.bond_friction_angle", params.bond_friction_angle, 0.0, np.pi / 2)
    lengths = {name: np.shape(getattr(params, name))[-1:]
               for name in ("kn", "ks", "friction", "youngs", "poisson")}
    if len(set(lengths.values())) > 1:
        raise InputError("params per-material arrays differ in length: "
                         + ", ".join(f"params.{k} {v}" for k, v in lengths.items()))
    # bond fields: all one value per member (the shape of dt), or all one per material
    member_shape = np.shape(params.dt)
    bond_shapes = {name: np.shape(value) for name, value in params._asdict().items()
                   if name.startswith("bond_")}
    allowed = (member_shape, member_shape + lengths["kn"])
    if len(set(bond_shapes.values())) > 1 or next(iter(bond_shapes.values())) not in allowed:
        raise InputError(f"params bond fields must all have shape {member_shape} (one value "
                         f"for all bonds) or all {member_shape + lengths['kn']} (one per "
                         "material), got " + ", ".join(f"params.{k} {v}"
                                                       for k, v in bond_shapes.items()))
    if dim is not None and np.shape(params.gravity)[-1:] != (dim,):
        raise InputError(f"params.gravity must have shape ({dim},), got {np.shape(params.gravity)}")


def read_text_file(path, what, kind):
    """The text of the input file ``path``, read as UTF-8 with a leading
    byte-order mark (as spreadsheet programs write) dropped.  A missing file, a
    folder or a binary file raises :class:`InputError` naming ``what`` (e.g.
    "target file") and ``kind`` (e.g. "CSV")."""
    path = pathlib.Path(path)
    if not path.exists():
        raise InputError(f"{what} {str(path)!r} does not exist")
    if not path.is_file():
        raise InputError(f"{what} {str(path)!r} is a directory, not a file")
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"{what} {str(path)!r} is not a text {kind} file ({e.reason} at "
                         f"byte {e.start})") from None
