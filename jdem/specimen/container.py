"""The specimen container (rectangle, box, disc), input checks, radius draws and
the loose random placement that starts a packing (steps 1–2 of the method in
:mod:`jdem.specimen`).

Citations ("002 §1.4") refer to the documents listed in REFERENCES.md.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from jdem.state import Bonds, Particles
from jdem.validate import InputError


SHAPES = ("rectangle", "box", "disc")
FLOATERS = ("attach", "remove", "keep")
_DIM = {"rectangle": 2, "box": 3, "disc": 2}
RSA_FRACTION = {2: 0.45, 3: 0.28}      # packing fraction of the loose RSA placement
MIN_POROSITY = {2: 0.10, 3: 0.25}      # targets below this are rejected up front
DISC_SIDES = 64


class Specimen(NamedTuple):
    """A generated specimen; see the module docstring for what each field holds."""

    particles: Particles
    bonds: Bonds
    box: tuple
    porosity: float
    coordination: float
    seed: int
    info: dict


class Container(NamedTuple):
    """The checked container: ``shape``, ``dim``, ``size`` [m], bounding box
    ``lo`` / ``hi`` (d,) [m], ``volume`` [m^2 x 1 m or m^3], and for a disc its
    ``centre`` (2,) and ``radius`` [m] (else None)."""

    shape: str
    dim: int
    size: tuple
    lo: np.ndarray
    hi: np.ndarray
    volume: float
    centre: np.ndarray | None
    radius: float | None


def finite_number(name, value):
    """``value`` as a finite float, else an InputError naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise InputError(f"{name} must be finite, got {value!r}")
    return v


def make_container(shape, size) -> Container:
    """The :class:`Container` of ``shape`` (one of :data:`SHAPES`) and ``size`` [m],
    checked."""
    if not isinstance(shape, str) or shape not in SHAPES:
        raise InputError(f"shape must be one of {SHAPES}, got {shape!r}")
    dim = _DIM[shape]
    want = {"rectangle": 2, "box": 3, "disc": 1}[shape]
    sz = np.atleast_1d(np.asarray(size, dtype=object)).tolist() if size is not None else []
    if len(sz) != want:
        what = {"rectangle": "(width, height)", "box": "(width, depth, height)",
                "disc": "the diameter (one number)"}[shape]
        raise InputError(f"size of a {shape!r} must be {what}, got {size!r}")
    vals = tuple(finite_number(f"size[{k}]" if want > 1 else "size", v) for k, v in enumerate(sz))
    for k, v in enumerate(vals):
        if v <= 0:
            raise InputError(f"{f'size[{k}]' if want > 1 else 'size'} must be > 0, got {v!r}")
    if shape == "disc":
        d = vals[0]
        return Container(shape, 2, vals, np.zeros(2), np.full(2, d), math.pi * d * d / 4,
                          np.full(2, d / 2), d / 2)
    hi = np.asarray(vals, float)
    return Container(shape, dim, vals, np.zeros(dim), hi, float(np.prod(hi)), None, None)


def check_inputs(c: Container, r_min, r_max, density, target_porosity, target_coordination,
                 gap_tolerance, overlap_limit, seed, floaters="attach"):
    """Check the inputs of :func:`jdem.specimen.generate`; InputError naming the
    field and the value."""
    r_min = finite_number("r_min", r_min)
    r_max = finite_number("r_max", r_max)
    if r_min <= 0:
        raise InputError(f"r_min must be > 0, got {r_min!r}")
    if r_max < r_min:
        raise InputError(f"r_max must be >= r_min = {r_min!r}, got {r_max!r}")
    smallest = min(c.size) if c.shape != "disc" else c.size[0]
    if smallest < 4 * r_max:
        raise InputError(f"size {c.size!r} is too small for particles of r_max = {r_max!r}: "
                         f"every side must be at least 4 r_max = {4 * r_max!r}")
    if np.any(~np.isfinite(np.asarray(density, float))) or np.any(np.asarray(density, float) <= 0):
        raise InputError(f"density must be > 0, got {density!r}")
    if target_porosity is not None:
        phi = finite_number("target_porosity", target_porosity)
        if not 0.0 < phi < 1.0:
            raise InputError(f"target_porosity must lie in (0, 1), got {phi!r}")
        if phi < MIN_POROSITY[c.dim]:
            raise InputError(
                f"target_porosity = {phi!r} is out of the reachable range: random packings of "
                f"{'discs' if c.dim == 2 else 'spheres'} without overlap are not denser than "
                f"porosity ~{MIN_POROSITY[c.dim]} (leave target_porosity=None for the densest)")
    if target_coordination is not None:
        z = finite_number("target_coordination", target_coordination)
        top = 6.0 if c.dim == 2 else 12.0
        if not 0.0 < z < top:
            raise InputError(f"target_coordination must lie in (0, {top}) in {c.dim}D, got {z!r}")
        if gap_tolerance is not None:
            raise InputError("give either gap_tolerance or target_coordination, not both "
                             f"(gap_tolerance = {gap_tolerance!r})")
    if gap_tolerance is not None:
        g = finite_number("gap_tolerance", gap_tolerance)
        if g < 0:
            raise InputError(f"gap_tolerance must be >= 0, got {g!r}")
    lim = finite_number("overlap_limit", overlap_limit)
    if not 0.0 < lim < 0.5:
        raise InputError(f"overlap_limit (a fraction of the mean radius) must lie in (0, 0.5), "
                         f"got {lim!r}")
    if floaters not in FLOATERS:
        raise InputError(f"floaters must be one of {FLOATERS}, got {floaters!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    return r_min, r_max


def particle_volume(r, dim):
    """Area pi r^2 (2D, unit thickness) or volume 4/3 pi r^3 (3D) of radii ``r``."""
    r = np.asarray(r, float)
    return np.pi * r**2 if dim == 2 else 4.0 / 3.0 * np.pi * r**3


def _mean_vol(r_min, r_max, dim):
    a, b = r_min, r_max
    if dim == 2:
        return np.pi * (a * a + a * b + b * b) / 3.0
    return np.pi * (a + b) * (a * a + b * b) / 3.0


def draw_radii(rng, r_min, r_max, dim, solid):
    """Uniform radii until their total area / volume is closest to ``solid``."""
    n_guess = int(1.2 * solid / _mean_vol(r_min, r_max, dim)) + 16
    rad = rng.uniform(r_min, r_max, size=n_guess)
    cum = np.cumsum(particle_volume(rad, dim))
    while cum[-1] < solid:  # (only for extreme draws) draw more, deterministically
        more = rng.uniform(r_min, r_max, size=n_guess)
        rad = np.concatenate([rad, more])
        cum = np.cumsum(particle_volume(rad, dim))
    k = int(np.searchsorted(cum, solid))  # cum[k] >= solid > cum[k-1]
    if k > 0 and solid - cum[k - 1] < cum[k] - solid:
        k -= 1
    n = max(k + 1, 2)
    return rad[:n].copy()


def wall_planes(c: Container):
    """Points on and inward normals of the container's walls."""
    if c.shape == "rectangle":
        w, h = c.size
        return [[0, 0], [w, 0], [0, 0], [0, h]], [[1, 0], [-1, 0], [0, 1], [0, -1]]
    if c.shape == "box":
        w, d, h = c.size
        pts = [[0, 0, 0], [w, 0, 0], [0, 0, 0], [0, d, 0], [0, 0, 0], [0, 0, h]]
        nrm = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
        return pts, nrm
    m = DISC_SIDES  # regular m-gon inscribed in the circle: its sides are the walls
    th = 2.0 * np.pi * (np.arange(m) + 0.5) / m
    out = np.stack([np.cos(th), np.sin(th)], axis=1)
    return c.centre + c.radius * math.cos(math.pi / m) * out, -out


def random_sequential_addition(rng, rad, c: Container, max_tries=20000, batch=8):
    """Random sequential addition of non-overlapping particles of radii ``rad``
    inside the container (largest first; a cell grid keeps it O(N))."""
    n = rad.size
    dim = c.dim
    lo, hi = c.lo, c.hi
    cell = 2.0 * rad.max()
    shape = np.maximum(1, np.ceil((hi - lo) / cell).astype(np.int64))
    k = int((cell / (2.0 * rad.min()) + 1.0) ** dim) + 1
    grid = np.full(tuple(shape + 2) + (k,), -1, np.int64)  # a ring of empty border cells
    count = np.zeros(tuple(shape + 2), np.int64)
    pos = np.zeros((n, dim))
    offs = np.stack(np.meshgrid(*[[-1, 0, 1]] * dim, indexing="ij"), -1).reshape(-1, dim)
    inner = None if c.radius is None else c.radius * math.cos(math.pi / DISC_SIDES)
    for idx in np.argsort(-rad, kind="stable"):
        r = rad[idx]
        for _ in range(max_tries // batch):
            cand = rng.uniform(lo + r, hi - r, size=(batch, dim))
            ok = np.ones(batch, bool)
            if inner is not None:
                ok &= np.sum((cand - c.centre) ** 2, axis=1) <= (inner - r) ** 2
            cc = np.minimum(np.floor((cand - lo) / cell).astype(np.int64) + 1, shape)
            nb = cc[:, None, :] + offs[None]
            ids = grid[tuple(nb[..., a] for a in range(dim))].reshape(batch, -1)
            there = ids >= 0
            safe = np.where(there, ids, 0)
            d2 = np.sum((pos[safe] - cand[:, None, :]) ** 2, axis=-1)
            ok &= ~np.any(there & (d2 < (rad[safe] + r) ** 2), axis=1)
            if ok.any():
                b = int(np.argmax(ok))
                pos[idx] = cand[b]
                key = tuple(cc[b])
                grid[key + (count[key],)] = idx
                count[key] += 1
                break
        else:
            raise RuntimeError(f"specimen: random placement failed after {max_tries} tries "
                               f"(particle {idx}, radius {r:.4g} m)")
    return pos
