"""The one-dimensional P-wave bar of 001 §2.2, Fig 1, on which the boundary
calibrations run (:func:`bar_model`, :func:`run_bar`, :func:`reflection`).

Citations ("001 eq 12") refer to the documents listed in REFERENCES.md.

The reflection of a boundary on a random packing is measured against an
extended reference model with the identical packing (:func:`bar_pair`,
:func:`reflection_against_reference`), so that what a random packing scatters
by itself cancels.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jdem.simulate import make_state, run
from jdem.specimen import subset
from jdem.state import Params
from jdem.validate import InputError, require_positive
from jdem.waves.boundaries import (BoundarySet, Conditions, activate, apply_conditions,
                                   boundary_particles, exposed_particles, make_boundary)
from jdem.waves.media import stable_dt, wave_params
from jdem.waves.monitors import Monitors, slice_groups
from jdem.waves.pulses import cosine_pulse, fix_driven, incident_wave, make_driven


class BarModel(NamedTuple):
    """The long bar of 001 Fig 1 (§2.2, §3.1), ready to run.

    state, params, config  the engine inputs (y fixed on every disc)
    conditions   Conditions(boundaries=(left, right), driven=(left drive,), loads=())
    monitors     Monitors: slices at ``monitor_x`` (the input and output boundary
                 discs at the ends)
    monitor_x    (5,) [m] positions P1..P5 along the bar
    length, height  [m];  c_p [m/s], density [kg/m^3] (nominal)
    amplitude, duration  the input pulse (001 eq 12) [m/s], [s]
    n_steps, record_every
    input        "velocity" (left discs driven) or "viscous" (001 eq 6)
    polarisation "P" (motion along the bar, x) or "S" (transverse, y)
    """

    state: object
    params: Params
    config: object
    conditions: Conditions
    monitors: Monitors
    monitor_x: np.ndarray
    length: float
    height: float
    c_p: float
    density: float
    amplitude: float
    duration: float
    n_steps: int
    record_every: int
    input: str
    polarisation: str = "P"



INPUTS = ("velocity", "viscous")
POLARISATIONS = ("P", "S")



def _motion(polarisation):
    """The component (0: x, 1: y) the discs of a bar of ``polarisation`` move in."""
    return 0 if polarisation == "P" else 1



def wave_speed(model: "BarModel") -> float:
    """The nominal speed [m/s] of the bar's wave: c_P, or c_S = c_P / sqrt 2 for
    an S bar (the value its boundaries use)."""
    return model.c_p if model.polarisation == "P" else model.c_p / math.sqrt(2.0)



def bar_model(particles, bonds, *, length, height, c_p=1000.0, density=2500.0, amplitude=0.5,
              duration=0.5, input="velocity", beta_left=1.0, beta_right=1.0, k_right=0.0,
              t_end=None, dt_factor=0.5, record_every=1, chunk_steps=2000, dt=None,
              right: BoundarySet | None = None, monitors: tuple | None = None,
              polarisation="P") -> BarModel:
    """The P-wave bar of 001 §2.2 on a given packing of [0, length] x [0, height].

    Every disc's y velocity is fixed (001 Fig 1).  The left boundary carries the
    input: ``input="velocity"`` drives its discs with the pulse of 001 eq 12
    (amplitude [m/s], duration [s]) — the "fixed" left end of 001 §2.2 —, or
    ``"viscous"`` makes it a viscous input boundary (001 eq 6) with beta_left.
    The right boundary is viscous (001 eq 4) with beta_right, viscoelastic when
    ``k_right`` [Pa/m] > 0 (001 eq 17).  Monitors P1..P5 every length/4 (001
    Fig 3) are slices one mean diameter wide; P1 and P5 are the boundary discs.
    ``t_end`` [s] defaults to the time the reflection from the right end takes to
    return to the middle and pass it, 2 length / c_p + duration.  ``dt`` is
    ``dt_factor`` x the critical step; ``n_steps`` is rounded up to whole chunks
    of ``chunk_steps`` so that every run of this size reuses one compiled chunk.
    ``dt`` [s] overrides the step (to run two models on the same clock),
    ``right`` (a :class:`BoundarySet`) the right boundary discs (default
    :func:`boundary_particles` on "right"), ``monitors`` (5 tuples of disc rows)
    the monitor groups P1..P5.

    ``polarisation="S"`` makes it the same bar for a transverse (S) pulse: every
    disc's x velocity is fixed instead, the pulse drives (or enters through) the
    left boundary along +y, the boundaries' tangential dashpots (beta_S D rho
    c_S, c_S = c_P / sqrt 2) absorb it, and ``t_end`` defaults to
    2 length / c_S + duration.  With bond nu = 0 and fixed rotations, a square
    arrangement of equal discs carries it at c_S (K_s = E_b / 2).
    """
    if input not in INPUTS:
        raise InputError(f"input must be one of {INPUTS}, got {input!r}")
    if polarisation not in POLARISATIONS:
        raise InputError(f"polarisation must be one of {POLARISATIONS}, got {polarisation!r}")
    along = _motion(polarisation)
    length = float(require_positive("length", length))
    height = float(require_positive("height", height))
    for name, v in (("amplitude", amplitude), ("duration", duration), ("dt_factor", dt_factor)):
        require_positive(name, v)
    if t_end is not None:
        require_positive("t_end", t_end)
    if chunk_steps % record_every:
        raise InputError(f"record_every = {record_every} must divide chunk_steps = {chunk_steps}")
    dtype = particles.pos.dtype
    params = wave_params(c_p, density)
    parts = particles._replace(fixed_vel=particles.fixed_vel.at[:, 1 - along].set(True))
    state, config = make_state(parts, bonds=bonds)
    step = stable_dt(state, params, config, dt_factor) if dt is None else float(
        require_positive("dt", dt))
    params = params._replace(dt=jnp.asarray(step, dtype))

    left = boundary_particles(parts, "left")
    right = boundary_particles(parts, "right") if right is None else right
    time, vel, disp = cosine_pulse(amplitude, duration)
    inward = np.eye(2)[along]                     # P: +x (the inward normal); S: +y
    c_s = c_p / math.sqrt(2.0)
    if input == "velocity":
        v_in, u_in = incident_wave(time, 0 * vel, 0 * disp, inward, dtype)
        drive = make_driven(left.index, time, vel, inward, mask=tuple(inward > 0), dtype=dtype)
        state = fix_driven(state, drive)
        beta_left = 0.0
    else:
        v_in, u_in = incident_wave(time, vel, disp, inward, dtype)
        drive = make_driven(left.index, time, 0 * vel, inward, mask=(False, False), dtype=dtype)
    lb = make_boundary(left, parts, density=density, c_p=c_p, c_s=c_s, beta_p=beta_left,
                       beta_s=beta_left, incident_vel=v_in, incident_disp=u_in)
    rb = make_boundary(right, parts, density=density, c_p=c_p, c_s=c_s, beta_p=beta_right,
                       beta_s=beta_right, k_n=k_right, k_s=k_right)
    cond = Conditions(boundaries=(lb, rb), driven=(drive,))
    # nothing is loaded yet (F_eq = 0); the fixity across the motion and the driven one stay
    state, cond = activate(state, params, config, cond, release=(False, False))

    x = np.linspace(0.0, length, 5)
    r_mean = float(np.mean(np.asarray(parts.radius)[np.asarray(parts.valid)]))
    groups = list(slice_groups(parts, 0, x, r_mean))
    groups[0] = tuple(int(k) for k in left.index)
    groups[-1] = tuple(int(k) for k in right.index)
    if monitors is not None:
        groups = [tuple(int(k) for k in g) for g in monitors]
    if t_end is None:
        t_end = 2.0 * length / (c_p if polarisation == "P" else c_s) + duration
    dt = float(params.dt)
    per_chunk = chunk_steps
    n_steps = int(math.ceil(t_end / dt / per_chunk)) * per_chunk
    return BarModel(state=state, params=params, config=config, conditions=cond,
                    monitors=Monitors(tuple(groups)), monitor_x=x, length=length, height=height,
                    c_p=float(c_p), density=float(density), amplitude=float(amplitude),
                    duration=float(duration), n_steps=n_steps, record_every=record_every,
                    input=input, polarisation=polarisation)



def with_betas(model: BarModel, *, beta_left=None, beta_right=None, wave="both") -> Conditions:
    """The model's conditions with new calibration factors of 001 eq 4: beta_2P
    (``wave="P"``), beta_2S (``"S"``) or both set to the value (``"both"``); the
    other factor keeps its value."""
    if wave not in ("both",) + POLARISATIONS:
        raise InputError(f"wave must be 'both', 'P' or 'S', got {wave!r}")
    left, right = model.conditions.boundaries
    f = lambda v: jnp.asarray(v, left.beta_p.dtype)   # noqa: E731
    names = {"both": ("beta_p", "beta_s"), "P": ("beta_p",), "S": ("beta_s",)}[wave]
    if beta_left is not None:
        left = left._replace(**{k: f(beta_left) for k in names})
    if beta_right is not None:
        right = right._replace(**{k: f(beta_right) for k in names})
    return model.conditions._replace(boundaries=(left, right))


def with_boundary_monitors(model: BarModel, side="right") -> BarModel:
    """The bar with one more monitor per disc of its ``side`` boundary ("left"
    or "right"), in the boundary's order (bottom to top), after P1..P5: a
    :func:`run_bar` history's ``vel[:, 5:]`` are those discs, for the peak
    velocity along the boundary (001 Fig 12)."""
    sides = ("left", "right")
    if side not in sides:
        raise InputError(f"side must be one of {sides}, got {side!r}")
    b = model.conditions.boundaries[sides.index(side)]
    groups = tuple(model.monitors.groups) + tuple((int(k),) for k in b.index)
    return model._replace(monitors=Monitors(groups))


def motion_direction(model: BarModel) -> np.ndarray:
    """Unit vector (2,) of the discs' motion in the bar: x for P, y for S."""
    return np.eye(2)[_motion(model.polarisation)]



def run_bar(model: BarModel, conditions: Conditions | None = None, *, n_steps=None,
            progress=False) -> dict:
    """Run the bar; returns the monitor history: ``time`` (R,) [s], ``vel`` and
    ``disp`` (R, 5, 2) at P1..P5 (displacement from the start) and
    ``state`` (the final state)."""
    cond = model.conditions if conditions is None else conditions
    n = model.n_steps if n_steps is None else int(n_steps)
    res = run(model.state, model.params, model.config, n, record_every=model.record_every,
              observe=model.monitors, chunk_steps=2000, progress=progress, desc="bar",
              boundary=(apply_conditions, cond))
    h = res.history
    pos0 = np.asarray(model.monitors(model.state, model.params, model.config)["pos"])
    return dict(time=h["time"], vel=h["vel"], disp=h["pos"] - pos0[None], state=res.state)



def peak(history: dict, monitor: int, direction=(1.0, 0.0)) -> float:
    """Largest velocity of monitor ``monitor`` along ``direction`` over the record [m/s]."""
    return float(np.max(history["vel"][:, monitor] @ np.asarray(direction, float)))



def reflection(history: dict, model: BarModel, monitor: int = 2) -> dict:
    """Incident and reflected amplitude at a monitor inside the bar (default P3).

    The incident peak ``incident`` is the largest x velocity (y for an S bar,
    whose nominal speed c_S replaces c_P below); the reflected
    amplitude ``reflected`` the largest |x velocity| after the incident pulse
    has passed (peak time + 0.6 T) and before the wave reflected at the right end
    can come back from the left end (peak time + 2 length / c - 0.6 T), with
    the wave speed c measured from the peak times at P2 and P3.  ``ratio`` =
    reflected / incident.
    """
    t = history["time"]
    v = history["vel"][:, :, _motion(model.polarisation)]
    x = model.monitor_x
    c = wave_speed(model)
    first = lambda k: t[int(np.argmax(np.where(t < x[k] / c + 2.0 * model.duration,
                                               v[:, k], -np.inf)))]
    t2, t3 = first(1), first(2)
    speed = (x[2] - x[1]) / (t3 - t2) if t3 > t2 else c
    tp = first(monitor)
    lo = tp + 0.6 * model.duration
    hi = tp + 2.0 * model.length / speed - 0.6 * model.duration   # back from the left end
    hi = min(hi, t[-1])
    win = (t >= lo) & (t <= hi)
    inc = float(np.max(v[:, monitor][t <= lo]))
    ref = float(np.max(np.abs(v[win, monitor]))) if np.any(win) else float("nan")
    return dict(incident=inc, reflected=ref, ratio=ref / inc, speed=float(speed),
                window=(float(lo), float(hi)))



def cut_packing(particles, bonds, x_max):
    """The discs of a packing whose centre lies at x <= ``x_max`` [m] and the
    bonds between them (rows renumbered, order kept; :func:`jdem.specimen.subset`).
    Returns ``(particles, bonds, rows)`` with ``rows`` (M,) the kept rows of the
    input, so that ``rows[k]`` is the original row of new disc k."""
    pos = np.asarray(particles.pos, np.float64)
    keep = np.asarray(particles.valid) & (pos[:, 0] <= float(x_max))
    if not keep.any():
        raise InputError(f"x_max = {x_max!r} keeps no particle")
    return subset(particles, bonds, keep)



class BarPair(NamedTuple):
    """A truncated bar and its extended reference (:func:`bar_pair`).

    truncated, reference  BarModels on one clock, with the same monitor discs
    clean_until  (5,) [s] at each monitor P1..P5, the earliest time anything
                 from the reference's far end could arrive there
    record       [s] the part of the record that counts, 2 length / c + T (c = c_P,
                 or c_S for an S bar)
    """

    truncated: BarModel
    reference: BarModel
    clean_until: np.ndarray
    record: float



def bar_pair(particles, bonds, *, length, height, monitor=2, c_max=None, **kwargs) -> BarPair:
    """A truncated bar and its extended reference, cut from one long packing.

    ``particles``, ``bonds``: a packing of [0, L_ext] x [0, height] [m]; the
    truncated model (:func:`bar_model`, same keywords) keeps the discs with
    centre x <= ``length`` [m] (:func:`cut_packing`), its right boundary the
    discs exposed on the cut (:func:`exposed_particles`; on a random packing
    the cut is ragged); the reference is the whole packing with the same left
    input, the same time step and record and the same monitor discs (P5: the
    truncated model's right boundary discs, inside the reference).  In
    [0, length] the two are the same disc for disc, so the packing's own
    scattering is the same in both.  The reference's far end (viscous,
    beta = 1) must be so far away that nothing from there reaches monitor
    ``monitor`` within the record 2 length / c + T (c_P, or c_S with
    ``polarisation="S"``): with the fastest speed
    ``c_max`` (default 1.2 c) it arrives at x_m after (2 L_ext - x_m) / c_max;
    InputError otherwise.  Returns a :class:`BarPair`.
    """
    kw = dict(kwargs)
    for name in ("dt", "right", "monitors", "t_end"):
        if name in kw:
            raise InputError(f"bar_pair sets {name} itself")
    parts, bnd, rows = cut_packing(particles, bonds, length)
    right = exposed_particles(parts, "right")
    params = wave_params(kw.get("c_p", 1000.0), kw.get("density", 2500.0))
    dts = []
    across = 1 - _motion(kw.get("polarisation", "P"))
    for p_, b_ in ((parts, bnd), (particles, bonds)):
        st, cf = make_state(p_._replace(fixed_vel=p_.fixed_vel.at[:, across].set(True)), bonds=b_)
        dts.append(stable_dt(st, params, cf, kw.get("dt_factor", 0.5)))
    dt = min(dts)                                 # one clock for both models
    trunc = bar_model(parts, bnd, length=length, height=height, right=right, dt=dt, **kw)
    t_end = (trunc.n_steps - 0.5) * dt            # the same whole chunks for the reference
    monitors = tuple(tuple(int(rows[k]) for k in g) for g in trunc.monitors.groups)
    ref = bar_model(particles, bonds, length=length, height=height, dt=dt, t_end=t_end,
                    monitors=monitors, **kw)
    if ref.n_steps != trunc.n_steps:
        raise RuntimeError("bar_pair: the two records differ in length")
    pos = np.asarray(particles.pos, np.float64)
    rad = np.asarray(particles.radius, np.float64)
    l_ext = float(np.max((pos[:, 0] + rad)[np.asarray(particles.valid)]))
    c = 1.2 * wave_speed(trunc) if c_max is None else float(require_positive("c_max", c_max))
    clean = (2.0 * l_ext - trunc.monitor_x) / c
    record = 2.0 * trunc.length / wave_speed(trunc) + trunc.duration
    if clean[monitor] < record:
        raise InputError(f"the packing is too short for a reference: its far end at {l_ext:.1f} m "
                         f"can reach monitor {monitor} after {clean[monitor]:.3f} s, within the "
                         f"record {record:.3f} s (need L_ext >= "
                         f"{0.5 * (c * record + trunc.monitor_x[monitor]):.1f} m)")
    return BarPair(truncated=trunc, reference=ref, clean_until=clean, record=record)



def reflection_against_reference(truncated: dict, reference: dict, *, monitor=2, incident=None,
                                 t_max=None, component=0) -> dict:
    """Reflected amplitude at a monitor, measured against an extended reference.

    ``truncated`` and ``reference`` are monitor histories (:func:`run_bar`) of
    the model with the absorbing boundary and of the extended model with the
    identical packing where they overlap (:func:`bar_pair`): ``time`` (R,) [s]
    on the same clock and ``vel`` (R, M, 2) [m/s] at the same monitor discs.
    Whatever the packing scatters by itself is in both and cancels; the
    difference is what the truncation sends back.  Only times t <= ``t_max``
    [s] count (default: the whole record; for a :class:`BarPair` pass
    ``pair.record``).  ``incident`` [m/s] is the peak incident amplitude
    (default: the largest ``component`` velocity of the reference at the
    monitor).  Returns ``reflected`` = max |v_truncated - v_reference| [m/s],
    ``incident``, ``ratio`` = reflected / incident, ``time`` [s] of the largest
    difference and ``difference`` (R,) [m/s] over the whole record.
    """
    ta, tb = np.asarray(truncated["time"]), np.asarray(reference["time"])
    if ta.shape != tb.shape or not np.allclose(ta, tb, rtol=1e-9, atol=0.0):
        raise InputError("truncated and reference records must share their time axis")
    va = np.asarray(truncated["vel"])[:, monitor, component]
    vb = np.asarray(reference["vel"])[:, monitor, component]
    diff = va - vb
    win = np.ones(ta.shape, bool) if t_max is None else ta <= float(t_max)
    if not np.any(win):
        raise InputError(f"t_max = {t_max!r} leaves no record")
    inc = float(np.max(vb[win])) if incident is None else float(
        require_positive("incident", incident))
    if not inc > 0:
        raise InputError(f"the reference never moves along component {component} at monitor "
                         f"{monitor} (peak {inc!r} m/s): for an S bar pass component=1")
    k = int(np.argmax(np.where(win, np.abs(diff), -np.inf)))
    ref = float(np.abs(diff[k]))
    return dict(incident=inc, reflected=ref, ratio=ref / inc, time=float(ta[k]), difference=diff)
