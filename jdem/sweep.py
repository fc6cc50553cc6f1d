"""Batched parameter sweeps of the platen tests, sharded over devices.

A sweep runs one laboratory test (a :mod:`jdem.lab` test object: uniaxial or
biaxial compression, Brazilian splitting, direct tension) on one specimen for
many sets of material parameters, as batches of the host loop
(:func:`jdem.lab.run`), and collects a table: the swept parameters, the key
figures of every curve (:func:`jdem.lab.peak_summary`) and the curves
themselves.

* :func:`grid` and :func:`latin_hypercube` make the samples (dict name -> (n,)).
* :func:`sweep` runs them and returns a :class:`SweepTable`.
* :func:`save_sweep` / :func:`load_sweep` write and read the table as HDF5;
  :func:`merge_sweeps` joins the parts written by several processes.
* :func:`jdem.plot.plot_sweep` draws a heat map (two parameters on a grid) or a curve
  (one parameter) of any column.

Parameter names are those of :data:`jdem.calibrate.PARAMETERS` (``E`` [Pa],
``nu``, ``T0`` [Pa], ``c0`` [Pa], ``phi`` [rad], ``eps_lim``, ``gamma_lim``,
and the tied pairs ``strength`` (T0 = c0) and ``kappa`` (eps_lim = gamma_lim));
:func:`jdem.calibrate.material` sets them, so the rock contacts follow E and nu.

Reproducibility.  The whole sweep uses one time step: the recommended step
(``jdem.timestep.recommended``) of the stiffest sample, i.e. the smallest over
all samples of the step the test's set-up would choose for it.
A member's result therefore does not depend on which other members share its
batch, up to round-off: the neighbour list of a batch is rebuilt when any
member needs it (the list is kept sorted, so this reorders no sum).

Round-off and chaos.  XLA compiles a batch of one member differently from a
batch of several, and a sharded program differently from an unsharded one of
the same local size, which changes the last bits of some intermediate values
(measured: 1e-26 in an angular velocity after 2 steps).  The explicit dynamics
of a breaking bonded packing under local (non-viscous) damping amplifies such
a difference about tenfold every 50 steps, so the post-peak curves of two
such runs differ visibly (164-disc UCS specimen: identical records up to step
450, then a 1e-11 relative difference growing to 1-25 % of the post-peak
stress; the peak stress differs by up to 2 %, the modulus by 1e-9).  On one
device, batches of 2, 3 and 4 copies of a sample gave bitwise-identical
members, and a sweep sharded so that every device holds one member
reproduces a one-device sweep with ``batch_size=1`` bitwise
(tests/test_sweep.py).  With smooth damping (``local_damping = 0``,
dashpots, the default :func:`jdem.lab.smooth`) the amplification
is far weaker (peak stress 6e-8, modulus 3e-16).

Sharding.  With ``shard=True`` and more than one device, every leaf of a
batch's state and params is placed with a :class:`jax.sharding.NamedSharding`
over a 1-D mesh of the devices, split along the leading (batch) axis; the
jitted chunks of :func:`jdem.run` then run each device's members on that
device.  Batches are padded to a multiple of the device count (and to one
common size, so that a single compiled chunk serves the whole sweep) by
repeating their last sample; the padding is dropped from the table.

Several processes.  Started under :func:`jax.distributed.initialize` (on a
cluster, one process per node or per accelerator), every process runs the
batches ``k`` with ``k % process_count == process_index`` on its own devices
(``jax.local_devices()``) and returns, and writes, its share: ``out`` becomes
``<stem>.process<i>of<n>.h5``.  :func:`merge_sweeps` joins the shares into the
whole table (rows in sample order, column ``sample``).  No data cross between
processes while they run, so nothing but the coordinator's address is needed.
"""
from __future__ import annotations

import json
import math
import pathlib
import time

import jax
import numpy as np

from jdem import lab
from jdem.batch import broadcast_batch
from jdem import io
from jdem.io import open_hdf5
from jdem.materials import PARAMETERS, material
from jdem.specimen import as_arrays
from jdem.validate import InputError, check_params

#: columns taken from :func:`jdem.lab.peak_summary`
SUMMARY_COLUMNS = ("peak_stress", "youngs_modulus", "critical_strain", "poisson_ratio",
                   "fracture_degree_at_peak", "fracture_degree_end", "final_stress")

#: file-format marker of :func:`save_sweep`
FORMAT = "jdem-sweep"


class SweepTable(dict):
    """The result of :func:`sweep`: a dict of NumPy columns plus ``attrs``.

    Columns (n = number of samples, R = records of the longest curve):

    <parameter>               (n,)   each swept parameter (SI units: Pa, rad, -)
    peak_stress               (n,)   largest axial stress [Pa] (Brazilian: load
                                     per metre of thickness [N/m])
    youngs_modulus            (n,)   slope over 10..40 % of the peak [Pa]
    critical_strain           (n,)   axial strain at the peak [-]
    poisson_ratio             (n,)   over the same records [-]
    fracture_degree_at_peak   (n,)   broken / initial bonds at the peak [-]
    fracture_degree_end       (n,)   the same at the end of the run [-]
    final_stress              (n,)   axial stress of the last record [Pa]
    tensile_strength          (n,)   Brazilian only: 2 P_peak / (pi D t) [Pa], t = 1 m
    n_records                 (n,)   valid records of each curve
    failed_step               (n,)   first step at which the sample's run failed
                                     the divergence guard and was set aside, -1
                                     for none (its figures are NaN then)
    strain, stress            (n, R) axial strain [-] and stress [Pa] per record,
                                     NaN after a member's last record

    ``attrs``: ``test``, ``parameters`` (swept names, in order), ``n_devices``,
    ``dt`` [s], ``wall_time`` [s], ``batch_size`` (members per compiled batch,
    padding included), ``n_batches``, ``steps`` (steps per member),
    ``member_steps_per_second``, ``loading_rate``, ``max_strain``,
    ``confining_stress`` [Pa] (0: none), ``record_every``, ``damping``,
    ``n_particles``, ``complete`` (False in a table saved while the sweep ran),
    ``failures`` (one line per failed sample: ``"sample k: reason"``).
    """

    def __init__(self, columns=(), attrs=None):
        super().__init__(columns)
        self.attrs = dict(attrs or {})

    @property
    def parameters(self) -> list:
        """The swept parameter names."""
        return list(self.attrs.get("parameters", ()))

    def __repr__(self):
        cols = ", ".join(f"{k}{tuple(np.shape(v))}" for k, v in self.items())
        return f"SweepTable({cols}; attrs={self.attrs!r})"


# ----------------------------------------------------------------------------- samples
def _axis_values(name, values):
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 0:
        a = a.reshape(1)
    if a.ndim != 1 or a.size == 0:
        raise InputError(f"axis {name!r} must be a non-empty 1-D sequence, got shape {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"axis {name!r}[{k}] must be finite, got {float(a[k])!r}")
    return a


def grid(**axes) -> dict:
    """Every combination of the given axis values (a full factorial design).

    ``grid(eps_lim=[1e-3, 3e-3], T0=[2e6, 4e6])`` -> ``{"eps_lim": (4,), "T0": (4,)}``
    with the first axis varying slowest (``numpy.meshgrid(indexing="ij")``
    order).  Each axis is a 1-D sequence (or a scalar, a fixed value).
    Returns dict name -> (prod of the axis lengths,) float64 array.
    """
    if not axes:
        raise InputError("grid needs at least one axis, e.g. grid(T0=[2e6, 4e6])")
    vals = [_axis_values(k, v) for k, v in axes.items()]
    mesh = np.meshgrid(*vals, indexing="ij")
    return {k: m.ravel() for k, m in zip(axes, mesh)}


def latin_hypercube(n: int, bounds: dict, seed: int = 0, log=None) -> dict:
    """A Latin-hypercube sample of ``n`` points.

    bounds   name -> (lo, hi), lo < hi, finite
    seed     seeds ``numpy.random.default_rng``: equal seeds (and bounds in the
             same order) give identical samples
    log      names sampled log-uniformly (their bounds must be > 0); ``True``
             for every name; ``None`` for none

    Each axis is cut into ``n`` strata of equal width (in log space for the
    ``log`` names); every stratum holds exactly one sample, placed uniformly at
    random inside it, and the strata are paired across axes by independent
    random permutations.  Returns dict name -> (n,) float64 array.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n must be an integer >= 1, got {n!r}")
    if not bounds:
        raise InputError("latin_hypercube needs bounds, e.g. {'T0': (1e6, 5e6)}")
    if log is True:
        log_names = set(bounds)
    elif log is None or log is False:
        log_names = set()
    else:
        log_names = {log} if isinstance(log, str) else set(log)
        unknown = log_names - set(bounds)
        if unknown:
            raise InputError(f"log names {sorted(unknown)} are not among the bounds "
                             f"{sorted(bounds)}")
    rng = np.random.default_rng(seed)
    out = {}
    for name, b in bounds.items():
        try:
            lo, hi = (float(x) for x in b)
        except (TypeError, ValueError):
            raise InputError(f"bounds[{name!r}] must be a pair (lo, hi), got {b!r}") from None
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise InputError(f"bounds[{name!r}] must be finite with lo < hi, got ({lo!r}, {hi!r})")
        if name in log_names and not lo > 0:
            raise InputError(f"bounds[{name!r}] = ({lo!r}, {hi!r}): a log-uniform axis needs lo > 0")
        u = (rng.permutation(n) + rng.random(n)) / n          # one point per stratum of [0, 1)
        if name in log_names:
            v = np.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        else:
            v = lo + u * (hi - lo)
        out[name] = np.clip(v, lo, hi)
    return out


# ----------------------------------------------------------------------------- checks
def _check_samples(samples) -> tuple[dict, int]:
    if not isinstance(samples, dict) or not samples:
        raise InputError("samples must be a non-empty dict name -> (n,) values, e.g. "
                         "sweep.grid(T0=[2e6, 4e6])")
    unknown = [k for k in samples if k not in PARAMETERS]
    if unknown:
        raise InputError(f"unknown parameter(s) {unknown} in samples; choose from "
                         f"{sorted(PARAMETERS)}")
    fields = {}
    for name in samples:
        for field in PARAMETERS[name]:
            if field in fields:
                raise InputError(f"samples {fields[field]!r} and {name!r} both set params.{field}")
            fields[field] = name
    out = {}
    n = None
    for name, v in samples.items():
        a = np.asarray(v, dtype=np.float64)
        if a.ndim != 1 or a.size == 0:
            raise InputError(f"samples[{name!r}] must be a non-empty 1-D array, got shape {a.shape}")
        if n is not None and a.size != n:
            raise InputError(f"samples[{name!r}] has {a.size} values, the others {n}")
        n = a.size
        bad = ~np.isfinite(a)
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(f"samples[{name!r}][{k}] must be finite, got {float(a[k])!r}")
        out[name] = a
    return out, n


def _batched_params(base_params, samples: dict, n: int):
    """``base_params`` repeated n times with the sampled values set; every bad
    value raises ``InputError`` naming the sample and the field."""
    if np.ndim(base_params.dt) != 0:
        raise InputError("base_params must be unbatched (one material; the samples make the "
                         f"batch), got params.dt of shape {np.shape(base_params.dt)}")
    check_params(base_params)
    batch = broadcast_batch(base_params, n)
    for name, v in samples.items():
        try:
            check_params(material(batch, {name: v}))
        except InputError as e:
            raise InputError(f"samples[{name!r}]: {e}") from None
    params = material(batch, samples)
    check_params(params)
    return params


def _layout(n: int, batch_size: int, n_dev: int) -> tuple[int, int]:
    """(members per batch, number of batches): as few batches as ``batch_size``
    allows, balanced, each a multiple of ``n_dev``."""
    n_batches = math.ceil(n / batch_size)
    per = math.ceil(n / n_batches)
    per = math.ceil(per / n_dev) * n_dev
    return per, math.ceil(n / per)


def _batch_indices(n: int, per: int, k: int) -> tuple[np.ndarray, int]:
    """Sample indices of batch ``k`` padded to ``per`` by repeating its last
    sample, and the number of real members."""
    idx = np.arange(k * per, min((k + 1) * per, n))
    real = idx.size
    return np.concatenate([idx, np.full(per - real, idx[-1])]), real


def _take(tree, idx):
    return jax.tree_util.tree_map(lambda a: a[idx], tree)


def _device_list(devices, shard):
    if not shard:
        return None
    devs = list(jax.local_devices() if devices is None else devices)
    if not devs:
        raise InputError("devices must name at least one device")
    return devs if len(devs) > 1 else None


def _placer(devs):
    """A function placing a batched pytree on the devices, split along the batch axis."""
    if devs is None:
        return lambda tree: tree
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    sharding = NamedSharding(Mesh(np.asarray(devs), ("batch",)), PartitionSpec("batch"))
    return lambda tree: jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding), tree)


# ----------------------------------------------------------------------------- running
def _test(test):
    if isinstance(test, str):
        if test not in lab.TESTS:
            raise InputError(f"test must be a jdem.lab test or one of {sorted(lab.TESTS)}, "
                             f"got {test!r}")
        return lab.TESTS[test]
    if not isinstance(test, lab.LabTest):
        raise InputError(f"test must be a jdem.lab test (e.g. jdem.lab.UCS), got {test!r}")
    return test


def sweep_timestep(specimen, params, *, test=lab.UCS, batch_size=16, **options) -> float:
    """The one time step [s] of a sweep: the smallest over the members of batched
    ``params`` of the step ``test.setup`` chooses (``jdem.timestep.recommended`` of
    the critical step with the platens, and lateral walls, in contact)."""
    test = _test(test)
    n = int(np.shape(params.dt)[0])
    best = np.inf
    for k in range(math.ceil(n / batch_size)):
        idx = np.arange(k * batch_size, min((k + 1) * batch_size, n))
        su = test.setup(specimen, _take(params, idx), **options)
        best = min(best, float(np.asarray(su.params.dt).reshape(-1)[0]))
    return best


def _check_options(batch_size, max_strain):
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
            or batch_size < 1:
        raise InputError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    if not (np.isfinite(max_strain) and max_strain > 0):
        raise InputError(f"max_strain must be > 0, got {max_strain!r}")


def sweep(specimen, base_params, samples: dict, *, test=lab.UCS, batch_size=16, shard=True,
          devices=None, max_strain=3e-3, stop_stress_ratio=None, dt=None, progress=True,
          out=None, chunk_records=None, save_every=60.0, resume=False,
          **options) -> SweepTable:
    """Run one lab test for every sample and tabulate the results.

    specimen        :class:`jdem.specimen.Specimen` (or ``(particles, bonds)``);
                    a 2D disc for :data:`jdem.lab.BRAZILIAN`
    base_params     unbatched ``Params`` of rock (material 0) and platen
                    (material 1), e.g. :func:`jdem.materials.rock_params`
    samples         dict name -> (n,) values (names from ``jdem.materials.PARAMETERS``;
                    e.g. from :func:`grid` or :func:`latin_hypercube`); each
                    sample overrides ``base_params`` via ``jdem.materials.material``
    test            a :mod:`jdem.lab` test object (``lab.UCS``, ``lab.BIAXIAL`` with
                    ``confining_stress=``, ``lab.BRAZILIAN``, ``lab.TENSION``), or its name
    batch_size      most members per vmapped batch (padding excluded)
    shard           split every batch over ``devices`` (default: all of this
                    process's ``jax.local_devices()``) along its batch axis when
                    there are several; under ``jax.distributed`` each process runs
                    its share of the batches (module docstring)
    max_strain      axial strain to load to
    stop_stress_ratio  stop a batch once all its members fell below this fraction
                    of their peak (None: run to ``max_strain``); shorter curves
                    are padded with NaN in the table
    dt              the time step [s]; default :func:`sweep_timestep` (the
                    stiffest sample's recommended step), used by every batch
    progress        a tqdm bar over the batches
    out             optional HDF5 path: the table is saved there (:func:`save_sweep`),
                    also every ``save_every`` seconds while the sweep runs and when it
                    is interrupted or fails (``attrs["complete"]`` False then)
    resume          continue the sweep saved at ``out`` (the same samples, test and
                    time step): batches already there are not run again
    chunk_records   records per jitted chunk of :func:`jdem.lab.run`
    options         passed to ``test.setup`` (``loading_rate`` or ``platen_step``,
                    ``confining_stress``, ``damping``, ``record_every``, ...)

    A member whose run fails (:func:`jdem.lab.run` sets it aside) keeps its row:
    NaN figures, ``failed_step`` its first bad step, the reason in
    ``attrs["failures"]``; the other samples are unaffected.

    Returns a :class:`SweepTable` (columns of shape (n,) and the curves (n, R)).
    Bad names or values raise ``jdem.validate.InputError`` naming them.
    """
    test = _test(test)
    _check_options(batch_size, max_strain)
    samples, n = _check_samples(samples)
    params = _batched_params(base_params, samples, n)
    options = dict(options, max_strain=max_strain)
    t_start = time.perf_counter()
    if dt is None:
        dt = sweep_timestep(specimen, params, test=test, batch_size=batch_size, **options)
    elif not (np.isfinite(dt) and dt > 0):
        raise InputError(f"dt must be > 0 [s] (or None), got {dt!r}")
    dt = float(dt)
    devs = _device_list(devices, shard)
    n_dev = len(devs) if devs else 1
    place = _placer(devs)
    per, n_batches = _layout(n, batch_size, n_dev)
    n_proc, proc = jax.process_count(), jax.process_index()
    if n_batches < n_proc:
        raise InputError(f"{n} samples make {n_batches} batch(es) of {per}, fewer than the "
                         f"{n_proc} processes; lower batch_size")
    mine = [k for k in range(n_batches) if k % n_proc == proc]

    n_particles = int(np.sum(np.asarray(as_arrays(specimen)[0].valid)))
    if out is not None and n_proc > 1:
        out = pathlib.Path(out)
        out = out.with_name(f"{out.stem}.process{proc}of{n_proc}{out.suffix}")
    done = _resumed(out, samples, n, dt, test.name) if resume else []
    if resume and out is None:
        raise InputError("resume=True needs out= (the table file to continue)")
    have = {int(k) for d in done for k in d["idx"]}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(mine), desc=f"sweep {test.name}", unit="batch", leave=False)
    plan = None
    meta = dict(test=test.name, parameters=list(samples), n_devices=n_dev, dt=dt,
                batch_size=per, n_batches=n_batches, n_samples=n, process_index=proc,
                process_count=n_proc, max_strain=float(max_strain),
                confining_stress=float(options.get("confining_stress") or 0.0),
                n_particles=n_particles)
    last_save = time.time()
    complete = False
    try:
        for k in mine:
            idx, real = _batch_indices(n, per, k)
            if bar is not None:
                bar.update(0)
            if set(int(i) for i in idx[:real]) <= have:   # in the resumed table
                if bar is not None:
                    bar.update(1)
                continue
            su = test.setup(specimen, _take(params, idx), dt=dt, **options)
            su = su.replace(state=place(su.state), params=place(su.params),
                            frame=place(su.frame))
            plan = su.plan
            res = lab.run(su, progress=False, stop_stress_ratio=stop_stress_ratio,
                          chunk_records=chunk_records)
            hist = {key: np.asarray(v)[:real] for key, v in res.history.items()}
            failed = hist.get("member_failed_step", np.full(real, -1))
            reasons = {int(idx[f.member]): f.reason for f in res.failures if f.member < real}
            steps = int(np.asarray(hist["step"]).max() - np.asarray(hist["step"]).min()
                        + plan.record_every)
            done.append(dict(idx=idx[:real], summary=lab.peak_summary(hist),
                             curve=(hist["axial_strain"], hist["axial_stress"]),
                             failed=np.asarray(failed), reasons=reasons, steps=steps))
            meta.update(loading_rate=float(plan.option("loading_rate")),
                        record_every=int(plan.record_every), damping=str(plan.damping))
            if out is not None and time.time() - last_save >= save_every:
                save_sweep(out, _table(samples, done, meta, t_start, complete=False))
                last_save = time.time()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(samples=f"{min((k + 1) * per, n)}/{n}")
        complete = True
    finally:
        if bar is not None:
            bar.close()
        if out is not None and done and not complete:   # interrupted or failed: keep what ran
            save_sweep(out, _table(samples, done, meta, t_start, complete=False))
    table = _table(samples, done, meta, t_start, complete=True)
    if out is not None:
        save_sweep(out, table)
    return table


def _table(samples, done, meta, t_start, complete) -> SweepTable:
    """The table of the batches run so far (``done``: one dict per batch), in
    the order they ran; a failed sample's figures are NaN."""
    wall = time.perf_counter() - t_start
    table = SweepTable()
    taken = np.concatenate([d["idx"] for d in done])
    table["sample"] = taken
    for name, v in samples.items():
        table[name] = v[taken].copy()
    rows = [d["summary"] for d in done]
    failed = np.concatenate([d["failed"] for d in done]).astype(np.int64)
    cols = SUMMARY_COLUMNS + (("tensile_strength",) if "tensile_strength" in rows[0] else ())
    for c in cols:
        v = np.concatenate([np.asarray(r[c], np.float64).reshape(-1) for r in rows])
        table[c] = np.where(failed >= 0, np.nan, v)
    curves = [d["curve"] for d in done]
    r_max = max(e.shape[1] for e, _ in curves)
    table["n_records"] = np.concatenate([d.get("n_records", np.full(d["curve"][0].shape[0],
                                                                    d["curve"][0].shape[1]))
                                         for d in done])
    for j, key in enumerate(("strain", "stress")):
        table[key] = np.concatenate([_pad_nan(c[j], r_max) for c in curves])
    table["failed_step"] = failed
    steps = max(d["steps"] for d in done)
    reasons = {k: r for d in done for k, r in d["reasons"].items()}
    table.attrs = dict(meta, wall_time=wall, steps=steps,
                       member_steps_per_second=taken.size * steps / wall, complete=complete,
                       failures=[f"sample {k}: {reasons[k]}" for k in sorted(reasons)])
    return table


def _resumed(out, samples, n, dt, test_name) -> list:
    """The batches of an earlier, interrupted sweep saved at ``out`` (same
    samples, test and time step), as :func:`_table` takes them; [] if there is
    no file."""
    if out is None or not pathlib.Path(out).exists():
        return []
    old = load_sweep(out)
    if old.attrs.get("test") != test_name or old.attrs.get("n_samples") != n \
            or not np.isclose(float(old.attrs.get("dt", np.nan)), dt, rtol=1e-12, atol=0):
        raise InputError(f"resume: {out} holds another sweep (test {old.attrs.get('test')!r}, "
                         f"{old.attrs.get('n_samples')} samples, dt {old.attrs.get('dt')}); "
                         f"this one is {test_name!r}, {n} samples, dt {dt}")
    for name, v in samples.items():
        if name not in old or not np.array_equal(old[name], v[old["sample"]]):
            raise InputError(f"resume: {out} was run with other values of {name!r}")
    idx = np.asarray(old["sample"])
    summary = {c: np.asarray(old[c]) for c in SUMMARY_COLUMNS + ("tensile_strength",) if c in old}
    reasons = {}
    for line in old.attrs.get("failures", []):
        head, _, why = line.partition(": ")
        reasons[int(head.split()[1])] = why
    m = np.asarray(old["n_records"])
    r = int(m.max())
    return [dict(idx=idx, summary=summary,
                 curve=(np.asarray(old["strain"])[:, :r], np.asarray(old["stress"])[:, :r]),
                 failed=np.asarray(old.get("failed_step", np.full(idx.size, -1))),
                 reasons=reasons, steps=int(old.attrs.get("steps", 0)), n_records=m)]


def merge_sweeps(parts, out=None) -> SweepTable:
    """One table from the shares of a multi-process sweep (tables or HDF5 paths
    written by :func:`sweep`): rows in sample order, curves padded with NaN to
    the longest.  Raises ``InputError`` when a sample is missing or repeated."""
    tables = [p if isinstance(p, SweepTable) else load_sweep(p) for p in parts]
    if not tables:
        raise InputError("merge_sweeps needs at least one table")
    n = int(tables[0].attrs.get("n_samples", sum(len(t["sample"]) for t in tables)))
    order = np.concatenate([np.asarray(t["sample"]) for t in tables])
    if sorted(order.tolist()) != list(range(n)):
        missing = sorted(set(range(n)) - set(order.tolist()))
        raise InputError(f"the parts hold samples {sorted(order.tolist())}, not 0..{n - 1} "
                         f"once each (missing {missing})")
    rank = np.argsort(order)
    r_max = max(np.asarray(t["strain"]).shape[1] for t in tables)
    merged = SweepTable()
    for key in tables[0]:
        cols = [np.asarray(t[key]) for t in tables]
        if cols[0].ndim == 2:
            cols = [_pad_nan(c, r_max) for c in cols]
        merged[key] = np.concatenate(cols)[rank]
    attrs = dict(tables[0].attrs)
    attrs.update(wall_time=max(float(t.attrs["wall_time"]) for t in tables),
                 n_devices=sum(int(t.attrs["n_devices"]) for t in tables),
                 process_index=0, process_count=len(tables),
                 complete=all(bool(t.attrs.get("complete", True)) for t in tables),
                 failures=[line for t in tables for line in t.attrs.get("failures", [])])
    attrs["member_steps_per_second"] = n * float(attrs["steps"]) / attrs["wall_time"]
    merged.attrs = attrs
    if out is not None:
        save_sweep(out, merged)
    return merged


def _pad_nan(a, r):
    a = np.asarray(a, np.float64)
    return np.concatenate([a, np.full((a.shape[0], r - a.shape[1]), np.nan)], axis=1)


# ----------------------------------------------------------------------------- HDF5
def save_sweep(path, table: SweepTable) -> pathlib.Path:
    """Write a :class:`SweepTable` to HDF5 with :func:`jdem.io.save_run`: one
    dataset per column in the history group ``table`` (in column order), the
    attributes on the root (lists as JSON) plus ``format = "jdem-sweep"``.
    Parent directories are created; an existing file is replaced.  Returns the
    path."""
    attrs = dict(getattr(table, "attrs", {}) or {})
    attrs["format"] = FORMAT
    return io.save_run(path, history={"table": {k: np.asarray(v) for k, v in table.items()}},
                       attrs=attrs)


def load_sweep(path) -> SweepTable:
    """Read a table written by :func:`save_sweep` (:func:`jdem.io.load_run`:
    columns as NumPy arrays with their stored dtype; attributes as Python
    values).  Tables of the first sweep format (a root ``/table`` group) load
    too."""
    path = pathlib.Path(path)
    with open_hdf5(path) as f:
        fmt = f.attrs.get("format")
        old = "table" in f and "_json_attrs" in f.attrs
    if fmt != FORMAT:
        raise InputError(f"{path} is not a sweep table (format attribute {fmt!r})")
    if old:
        return _load_sweep_v1(path)
    rd = io.load_run(path, numpy=True)
    if "table" not in (rd.history or {}):
        raise InputError(f"{path} is not a sweep table (no history group 'table')")
    attrs = {k: v for k, v in (rd.attrs or {}).items() if k != "format"}
    return SweepTable(dict(rd.history["table"]), attrs)


def _load_sweep_v1(path) -> SweepTable:
    with open_hdf5(path) as f:
        json_keys = set(json.loads(f.attrs.get("_json_attrs", "[]")))
        attrs = {}
        for key, value in f.attrs.items():
            if key in ("format", "format_version", "_json_attrs"):
                continue
            value = value.item() if isinstance(value, np.generic) else value
            attrs[key] = json.loads(value) if key in json_keys else value
        columns = {key: io.read_dataset(ds) for key, ds in f["table"].items()}
    return SweepTable(columns, attrs)
