"""Broken bonds and damage of a state, for failure patterns (002 Fig. 12) and
damage maps (002 Fig. 13).
Citations ("002 Fig. 12") refer to the documents listed in REFERENCES.md."""
from __future__ import annotations

import numpy as np

from jdem import bond as bond_mod
from jdem.batch import member
from jdem.validate import InputError


def bond_points(state):
    """Contact point (B, d) of every bond row (dividing the centre line R1 : R2),
    the unit branch vector (B, d) and the half width min(R1, R2) (B,) of the
    bar; NumPy, one (unbatched) state."""
    p = state.particles
    b = state.bonds
    pos = np.asarray(p.pos, np.float64)
    rad = np.asarray(p.radius, np.float64)
    i, j = np.asarray(b.i), np.asarray(b.j)
    r1, r2 = rad[i], rad[j]
    dx = pos[j] - pos[i]
    length = np.where(r1 + r2 > 0, r1 + r2, 1.0)
    point = pos[i] + (r1 / length)[:, None] * dx
    dist = np.linalg.norm(dx, axis=1)
    nrm = dx / np.where(dist > 0, dist, 1.0)[:, None]
    return point, nrm, np.minimum(r1, r2)


def _check_unbatched(state, name):
    if np.ndim(state.step) != 0:
        raise InputError(f"{name} takes one (unbatched) state; pick a member with "
                         f"jdem.member(state, b)")


def failure_pattern(state) -> dict:
    """The broken bonds of a state.

    index    (n,)       bond rows that are broken
    point    (n, d)     contact point of the bar [m]
    segment  (n, 2, d)  2D: the crack face, the bar's cross-section (length
                        2 min(R1, R2), perpendicular to the bond) through ``point``;
                        3D: the bond's centre line between the centres
    mode     (n,)       1 tension, 2 shear (``Bonds.break_mode``)
    step     (n,)       step at which it broke
    """
    _check_unbatched(state, "failure_pattern")
    b = state.bonds
    point, nrm, half = bond_points(state)
    broken = np.asarray(b.valid) & np.asarray(b.broken)
    idx = np.nonzero(broken)[0]
    if point.shape[1] == 2:
        tang = np.stack([-nrm[:, 1], nrm[:, 0]], axis=1)
        seg = np.stack([point - half[:, None] * tang, point + half[:, None] * tang], axis=1)
    else:
        pos = np.asarray(state.particles.pos, np.float64)
        seg = np.stack([pos[np.asarray(b.i)], pos[np.asarray(b.j)]], axis=1)
    return dict(index=idx, point=point[idx], segment=seg[idx],
                mode=np.asarray(b.break_mode)[idx], step=np.asarray(b.break_step)[idx])


def first_breaks(pattern: dict, fraction: float = 0.1, minimum: int = 5) -> np.ndarray:
    """Where a failure starts: indices into the arrays of :func:`failure_pattern`
    of its earliest broken bonds, the first ``fraction`` of them by breaking step
    but at least ``minimum`` (all of them if fewer broke)."""
    n = len(pattern["step"])
    count = max(int(minimum), int(np.floor(n * float(fraction) + 1e-9)))
    return np.argsort(pattern["step"], kind="stable")[:count]


def damage_map(state) -> dict:
    """Every valid bond's contact point and damage (002 eq 10): ``point`` (B, d),
    ``chi``, ``alpha``, ``beta`` (B,), ``broken`` (B,) bool, ``mode`` (B,) and
    ``index`` (B,) of the rows."""
    _check_unbatched(state, "damage_map")
    b = state.bonds
    point, _, _ = bond_points(state)
    valid = np.asarray(b.valid)
    idx = np.nonzero(valid)[0]
    dmg = {k: np.asarray(v) for k, v in bond_mod.damage(b).items()}
    return dict(index=idx, point=point[idx], chi=dmg["chi"][idx], alpha=dmg["alpha"][idx],
                beta=dmg["beta"][idx], broken=np.asarray(b.broken)[idx],
                mode=np.asarray(b.break_mode)[idx])


def bond_record(state, prefix):
    """Per-bond arrays of a state (batched or not) for a history: ``<prefix>point``
    (contact points), ``chi``, ``mode`` (0 intact, 1 tension, 2 shear),
    ``break_step`` and ``valid`` of every bond row."""
    batched = np.ndim(state.step) == 1
    members = [member(state, k) for k in range(state.step.shape[0])] if batched else [state]
    out = {f"{prefix}{k}": [] for k in ("point", "chi", "mode", "break_step", "valid")}
    for s in members:
        point, _, _ = bond_points(s)
        out[f"{prefix}point"].append(point)
        out[f"{prefix}chi"].append(np.asarray(bond_mod.damage(s.bonds)["chi"]))
        broken = np.asarray(s.bonds.broken)
        out[f"{prefix}mode"].append(np.where(broken, np.asarray(s.bonds.break_mode), 0))
        out[f"{prefix}break_step"].append(np.asarray(s.bonds.break_step))
        out[f"{prefix}valid"].append(np.asarray(s.bonds.valid))
    return {k: (np.stack(v) if batched else v[0]) for k, v in out.items()}
