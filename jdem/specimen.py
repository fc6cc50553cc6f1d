"""Rock specimen generation (prototype)."""
from __future__ import annotations

import math
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import neighbors
from jdem.kinematics import dot, safe_norm
from jdem.measure import kinetic_energy
from jdem.state import Bonds, Config, Particles, make_params, make_particles, make_walls
from jdem.simulate import make_state, run
from jdem.validate import InputError

SHAPES = {"rectangle": 2, "box": 3, "disc": 2}
RSA_FRACTION = {2: 0.30, 3: 0.18}


def _observe(state, params, config):
    p = state.particles
    c = state.contacts
    dist = safe_norm(p.pos[c.j] - p.pos[c.i])
    ov = jnp.where(c.valid, p.radius[c.i] + p.radius[c.j] - dist, 0.0)
    w = state.walls
    dw = dot(p.pos[None] - w.point[:, None], w.normal[:, None])
    ovw = jnp.where(p.valid[None] & w.valid[:, None], p.radius[None] - dw, 0.0)
    return dict(max_overlap=jnp.maximum(jnp.max(ov, initial=0.0), jnp.max(ovw, initial=0.0)),
                kinetic=kinetic_energy(state),
                n_touch=jnp.sum(ov > 0))


def _vol(r, dim):
    return np.pi * r**2 if dim == 2 else 4.0 / 3.0 * np.pi * r**3


def _rsa(rng, rad, lo, hi, disc=None, max_tries=5000, batch=8):
    """Random sequential addition of non-overlapping spheres inside [lo, hi]
    (and inside the disc (centre, R) if given).  Places largest first."""
    n = rad.size
    dim = lo.size
    cell = 2.0 * rad.max()
    shape = np.maximum(1, np.ceil((hi - lo) / cell).astype(np.int64))
    k = int((cell / (2.0 * rad.min()) + 1.0) ** dim) + 1
    grid = np.full(tuple(shape + 2) + (k,), -1, np.int64)  # +2: a border ring of empty cells
    count = np.zeros(tuple(shape + 2), np.int64)
    pos = np.zeros((n, dim))
    offs = np.array(np.meshgrid(*[[-1, 0, 1]] * dim, indexing="ij")).reshape(dim, -1).T
    order = np.argsort(-rad, kind="stable")
    for idx in order:
        r = rad[idx]
        placed = False
        for _ in range(max_tries // batch):
            cand = rng.uniform(lo + r, hi - r, size=(batch, dim))
            ok = np.ones(batch, bool)
            if disc is not None:
                c, big_r = disc
                ok &= np.sum((cand - c) ** 2, axis=1) <= (big_r - r) ** 2
            cc = np.floor((cand - lo) / cell).astype(np.int64) + 1
            cc = np.minimum(cc, shape)
            nb = cc[:, None, :] + offs[None]  # (batch, 3^d, d)
            ids = grid[tuple(nb[..., a] for a in range(dim))].reshape(batch, -1)
            m = ids >= 0
            safe = np.where(m, ids, 0)
            d2 = np.sum((pos[safe] - cand[:, None, :]) ** 2, axis=-1)
            hit = m & (d2 < (rad[safe] + r) ** 2)
            ok &= ~hit.any(axis=1)
            if ok.any():
                b = int(np.argmax(ok))
                pos[idx] = cand[b]
                key = tuple(cc[b])
                if count[key] >= k:
                    raise RuntimeError("RSA grid overflow")
                grid[key + (count[key],)] = idx
                count[key] += 1
                placed = True
                break
        if not placed:
            raise RuntimeError("RSA failed")
    return pos


def _container_walls(shape, size, n):
    if shape == "rectangle":
        w, h = size
        pts = [[0, 0], [w, 0], [0, 0], [0, h]]
        nrm = [[1, 0], [-1, 0], [0, 1], [0, -1]]
    elif shape == "box":
        w, d, h = size
        pts = [[0, 0, 0], [w, 0, 0], [0, 0, 0], [0, d, 0], [0, 0, 0], [0, 0, h]]
        nrm = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    else:
        big_r = 0.5 * size[0]
        m = 64
        th = 2 * np.pi * (np.arange(m) + 0.5) / m
        out = np.stack([np.cos(th), np.sin(th)], 1)
        pts = big_r + big_r * np.cos(np.pi / m) * out
        nrm = -out
    return make_walls(pts, nrm, n_particles=n)


def compact(shape, size, rad, pos0, s0, *, n_stage=200, g=0.01, limit=0.01, progress=False,
            kn=1e7, max_relax=2000, verbose=True):
    dim = pos0.shape[1]
    n = rad.size
    r_mean = rad.mean()
    m0 = 1.0
    p = make_particles(pos0, rad * s0)
    p = p._replace(mass=jnp.full_like(p.mass, m0), inertia=jnp.full_like(p.inertia, m0 * r_mean**2 / 2))
    pf = p._replace(radius=jnp.asarray(rad, p.radius.dtype))
    walls = _container_walls(shape, size, n)
    skin = 0.3 * r_mean
    lo = np.zeros(dim)
    hi = np.asarray(size if shape != "disc" else (size[0], size[0]), float)
    origin, gshape, cell = neighbors.grid_for(pf, skin=skin, extra_bounds=(lo, hi))
    kcell = int(math.ceil(cell**dim * 0.95 / _vol(rad.min(), dim))) + 2
    cfg = Config(dim=dim, skin=skin, cell_size=cell, grid_origin=origin, grid_shape=gshape,
                 max_per_cell=kcell)
    state, cfg = make_state(p, cfg, walls=walls)
    contacts, cfg = neighbors.allocate(p, cfg, min_capacity=(5 if dim == 2 else 10) * n)
    state = state._replace(contacts=contacts)
    params = make_params(dim, kn=kn, ks=kn * 1e-3, friction=0.0, local_damping=0.7)
    from jdem.timestep import nominal_critical_timestep
    crit = float(nominal_critical_timestep(pf, params, cfg, coordination=6 if dim == 2 else 12))
    dt = 0.6 * crit
    params = params._replace(dt=jnp.asarray(dt, params.dt.dtype),
                             viscous_damping=jnp.asarray(0.002 / dt, params.dt.dtype))
    s = s0
    steps = 0
    t0 = time.time()
    mo = 0.0
    hold = 0
    while True:
        if mo <= limit and s < 1.0:
            s = min(1.0, s * (1 + g))
            hold = 0
            state = state._replace(particles=state.particles._replace(radius=jnp.asarray(rad * s, p.radius.dtype)))
        else:
            hold += 1
        res = run(state, params, cfg, n_stage, record_every=n_stage, observe=_observe, progress=False)
        state, cfg = res.state, res.config
        steps += n_stage
        mo = float(res.history["max_overlap"][-1]) / r_mean
        if verbose:
            print(f"s={s:.4f} steps={steps} maxov={mo:.4f} ke={res.history['kinetic'][-1]:.3g} touch={res.history['n_touch'][-1]} t={time.time()-t0:.1f}")
        if s >= 1.0 and mo <= 0.5 * limit:
            break
        if hold * n_stage > max_relax:
            print("JAMMED at", s)
            break
    return state, steps, mo
