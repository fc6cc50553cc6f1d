"""Save, load and restart a run: one HDF5 file per snapshot (h5py).

File layout (format version 2)::

    /                     root attrs: ``format_version`` (int), ``jdem_version`` (str),
                          plus the user's ``attrs`` (str/int/float/bool values; lists
                          and tuples as JSON)
    /attrs/<name>         a group per ``attrs`` entry that is a dict: its entries
                          as attributes, nested dicts as sub-groups
    /state                group, attr ``_class = "State"``
        /particles        group, attr ``_class = "Particles"``
            pos           dataset (N, d), dtype as in memory
            ...           one dataset per field, in field order
        /contacts, /walls, /bonds   likewise
        step, time, first_bad_step  0-d datasets
    /params               group, attr ``_class = "Params"``; one dataset per field
    /config               group with no datasets: one attribute per dataclass field,
                          attr ``_class = "Config"``; fields that are not plain
                          str/int/float/bool (tuples) are stored as JSON strings and
                          listed in attr ``_json_fields``
    /history              one dataset per entry (insertion order kept); any shape,
                          e.g. a leading batch axis; an entry that is a dict is a
                          sub-group of datasets (nested dicts nest further)

Groups and attributes give a file its structure (``/history/iterations/loss``,
``/attrs/fit`` with one attribute per fitted parameter) rather than prefixes in
flat names; :func:`load_run` gives nested groups back as nested dicts.  Format
version 1 (no nested groups) still loads.  A calibration
(:func:`jdem.calibrate.save_calibration`), a ``jdem ucs`` run (attribute groups
``settings`` and ``summary``) and a lab checkpoint (history group ``raw``,
attribute group ``lab``) and a sweep table (history group ``table``, one dataset
per column; root attribute ``format = "jdem-sweep"``) are written this way.
With plain h5py::

    import h5py
    with h5py.File("calibration.h5") as f:
        fitted = dict(f["attrs/fit"].attrs)              # {"E": 3.0e10, ...}
        loss = f["history/iterations/loss"][()]          # per iteration
        fit_curve = f["history/curves/fit_stress"][()]

Every array keeps its dtype (bool, int32, float64, ...), its shape (0-d and
zero-length included) and its exact bits.  Arrays larger than 1 MiB are gzip
compressed, smaller ones are stored plain.  A NamedTuple group is rebuilt from
the class in :mod:`jdem.state` named by its ``_class`` attribute.

Files are written to a temporary name beside the target and then renamed, so an
interrupted save never destroys an older snapshot of the same name.

A run restarted from a file continues bit for bit on the CPU.  On a GPU the
force sums are atomic scatter-adds that sum in no fixed order, so two runs (and
a restart) agree only to round-off, which contacts amplify; set
``XLA_FLAGS=--xla_gpu_deterministic_ops=true`` before JAX starts for bit-for-bit
restarts there (at a large cost in speed, experiments/results/NOTES.md).
"""
from __future__ import annotations

import dataclasses
import json
import os
import pathlib
from typing import Any, NamedTuple

import h5py
import jax.numpy as jnp
import numpy as np

from jdem import state as _state_mod
from jdem.validate import InputError

FORMAT_VERSION = 2
COMPRESS_ABOVE_BYTES = 1 << 20  # gzip only arrays larger than 1 MiB
_RESERVED_ROOT_ATTRS = ("format_version", "jdem_version", "_json_fields")
_SCALAR_TYPES = (str, bool, int, float, np.bool_, np.integer, np.floating)


class CorruptFileError(InputError):
    """The file exists but is not a readable jdem HDF5 file (not HDF5, truncated,
    or missing a group / dataset); the message names the path and the problem."""


class RunData(NamedTuple):
    """What :func:`load_run` returns; any part that was not saved is ``None``."""

    state: Any          # jdem.state.State (or None)
    params: Any         # jdem.state.Params (or None)
    config: Any         # jdem.state.Config (or None)
    history: Any        # dict[str, jax.Array] (or None)
    attrs: Any          # dict[str, str | int | float | bool] (or None)


def _jdem_version() -> str:
    try:
        import jdem
        return str(getattr(jdem, "__version__", "unknown"))
    except Exception:  # pragma: no cover - jdem is importable if we are
        return "unknown"


# ----------------------------------------------------------------------------- writing

def write_dataset(group: h5py.Group, name: str, value) -> None:
    """One dataset; numeric arrays carry a Fletcher-32 checksum (h5py's
    ``fletcher32`` filter, checked on every read) and are gzip-compressed
    above ``COMPRESS_ABOVE_BYTES``.  Scalars cannot carry filters in HDF5."""
    a = np.asarray(value)
    filtered = a.ndim > 0 and a.size > 0 and a.dtype.kind in "biufc"
    big = a.nbytes > COMPRESS_ABOVE_BYTES
    group.create_dataset(name, data=a, compression="gzip" if big and filtered else None,
                         fletcher32=filtered)


def read_dataset(ds: h5py.Dataset) -> np.ndarray:
    """A dataset as NumPy; a checksum mismatch (a damaged file) raises
    :class:`CorruptFileError` naming the dataset and the file."""
    try:
        return np.asarray(ds[()])
    except OSError as err:
        raise CorruptFileError(f"dataset {ds.name!r} of {ds.file.filename} is damaged (its "
                               f"checksum or compressed data does not read back): {err}") from None



def _write_tree(group: h5py.Group, tree) -> None:
    """One sub-group per nested NamedTuple, one dataset per array leaf."""
    if not hasattr(tree, "_fields"):
        raise InputError(f"expected a NamedTuple to save, got {type(tree).__name__}")
    group.attrs["_class"] = type(tree).__name__
    for name, value in zip(tree._fields, tree):
        if isinstance(value, tuple) and hasattr(value, "_fields"):
            _write_tree(group.create_group(name), value)
        else:
            write_dataset(group, name, value)


def _write_attrs(attrs: h5py.AttributeManager, mapping: dict, what: str) -> None:
    """Plain scalars as native attributes; anything else (tuples) as JSON."""
    json_fields = []
    for key, value in mapping.items():
        if not isinstance(key, str) or not key or key.startswith("_"):
            raise InputError(f"{what} key must be a non-empty str not starting with '_', got {key!r}")
        if isinstance(value, _SCALAR_TYPES):
            attrs[key] = value
        else:
            try:
                attrs[key] = json.dumps(value, allow_nan=True,
                                        default=lambda o: o.item() if hasattr(o, "item") else o.tolist())
            except (TypeError, AttributeError) as e:
                raise InputError(f"{what}[{key!r}] cannot be stored: {value!r} ({e})") from None
            json_fields.append(key)
    if json_fields:
        attrs["_json_fields"] = json.dumps(json_fields)


def _check_names(tree: dict, what: str) -> None:
    """Names of a (nested) dict that become HDF5 names: non-empty str without '/'."""
    bad = [k for k in tree if not isinstance(k, str) or not k or "/" in k or k == "."]
    if bad:
        raise InputError(f"{what} names must be non-empty str without '/', got {bad!r}")
    for k, v in tree.items():
        if isinstance(v, dict):
            _check_names(v, f"{what}[{k!r}]")


def _write_history(group: h5py.Group, tree: dict) -> None:
    for name, value in tree.items():
        if isinstance(value, dict):
            _write_history(group.create_group(name, track_order=True), value)
        else:
            write_dataset(group, name, value)


def _write_attr_tree(node, mapping: dict, what: str) -> None:
    """Plain values of ``mapping`` as attributes of ``node`` (a file or group),
    dicts as sub-groups, recursively."""
    _write_attrs(node.attrs, {k: v for k, v in mapping.items() if not isinstance(v, dict)}, what)
    for name, value in mapping.items():
        if isinstance(value, dict):
            _write_attr_tree(node.create_group(name, track_order=True), value,
                             f"{what}[{name!r}]")


def save_run(path, *, state=None, params=None, config=None, history=None, attrs=None,
             overwrite: bool = True) -> pathlib.Path:
    """Write any of ``state``, ``params``, ``config``, ``history`` (dict name -> array,
    numpy or JAX) and root ``attrs`` (flat dict of str/int/float/bool) to ``path``.

    Parent directories are created.  With ``overwrite=False`` an existing file raises
    ``FileExistsError``.  Returns the path written.
    """
    path = pathlib.Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists and overwrite=False")
    attrs = dict(attrs or {})
    clash = set(attrs) & set(_RESERVED_ROOT_ATTRS)
    if clash:
        raise InputError(f"attrs may not use the reserved names {sorted(clash)}")
    if history is not None:
        _check_names(history, "history")
    _check_names({k: v for k, v in attrs.items() if isinstance(v, dict)}, "attrs")

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["jdem_version"] = _jdem_version()
            _write_attrs(f.attrs, {k: v for k, v in attrs.items() if not isinstance(v, dict)},
                         "attrs")
            nested = {k: v for k, v in attrs.items() if isinstance(v, dict)}
            if nested:   # under /attrs, apart from the state / params / ... groups
                _write_attr_tree(f.create_group("attrs", track_order=True), nested, "attrs")
            if state is not None:
                _write_tree(f.create_group("state"), state)
            if params is not None:
                _write_tree(f.create_group("params"), params)
            if config is not None:
                g = f.create_group("config")
                g.attrs["_class"] = type(config).__name__
                _write_attrs(g.attrs, {fl.name: getattr(config, fl.name)
                                       for fl in dataclasses.fields(config)}, "config")
            if history is not None:
                _write_history(f.create_group("history", track_order=True), history)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# ----------------------------------------------------------------------------- reading

def _to_py(value):
    return value.item() if isinstance(value, np.generic) else value


def _tuples(value):
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _read_attrs(attrs: h5py.AttributeManager, skip=("_class",), tuples=True) -> dict:
    """Attributes as Python values; JSON ones decoded, their lists as tuples
    (``tuples``: a Config's fields must be hashable) or as lists (user attrs)."""
    json_fields = set(json.loads(attrs.get("_json_fields", "[]")))
    out = {}
    for key, value in attrs.items():
        if key in skip or key == "_json_fields":
            continue
        value = _to_py(value)
        if key in json_fields:
            value = json.loads(value)
            value = _tuples(value) if tuples else value
        out[key] = value
    return out


class PrecisionError(InputError):
    """A file holds float64 arrays but this process runs JAX in float32, so
    loading would round them (and a restart would not continue bit for bit)."""


def _x64() -> bool:
    import jax

    return bool(jax.config.read("jax_enable_x64"))


def _read_array(ds: h5py.Dataset, allow_downcast=False):
    a = read_dataset(ds)
    if a.dtype == np.float64 and not allow_downcast and not _x64():
        raise PrecisionError(
            f"{ds.name} in {ds.file.filename} is float64 but JAX runs in float32 here "
            f"(jax_enable_x64 is off): loading would round it.  Enable float64 first "
            f"(jax.config.update('jax_enable_x64', True)), or pass allow_downcast=True")
    return jnp.asarray(a)


def _read_history(group: h5py.Group, numpy=False, allow_downcast=False) -> dict:
    read = read_dataset if numpy else lambda d: _read_array(d, allow_downcast)
    return {k: _read_history(v, numpy, allow_downcast) if isinstance(v, h5py.Group) else read(v)
            for k, v in group.items()}


def _read_attr_tree(group: h5py.Group) -> dict:
    """What :func:`_write_attr_tree` wrote: attributes, and sub-groups as dicts."""
    out = _read_attrs(group.attrs, tuples=False)
    out.update({name: _read_attr_tree(sub) for name, sub in group.items()})
    return out


def _class_of(group: h5py.Group, default: str, where: str, path) -> type:
    """The class named by the group's ``_class`` attr (else ``default``): a
    container of ``jdem.state`` or of ``jdem.blocks`` (block states and params
    are saved and restarted the same way)."""
    name = _to_py(group.attrs.get("_class", default))
    cls = getattr(_state_mod, str(name), None)
    if cls is None:
        import jdem.blocks as _blocks_mod

        cls = getattr(_blocks_mod, str(name), None)
    if not isinstance(cls, type):
        raise CorruptFileError(f"{where}: unknown class {name!r} in {path}")
    return cls


_LOW_PARTS = {"pos_lo": "pos", "point_lo": "point"}   # low part -> its high part


def _read_tree(group: h5py.Group, cls: type, where: str, path, allow_downcast=False):
    values = []
    for name in cls._fields:
        sub = f"{where}/{name}"
        if name not in group and name in _LOW_PARTS and _LOW_PARTS[name] in group:
            # written before positions were compensated pairs (jdem.precision):
            # the stored coordinate is the whole position
            values.append(np.zeros_like(_read_array(group[_LOW_PARTS[name]], allow_downcast)))
            continue
        if name not in group:
            raise CorruptFileError(f"{sub} missing in {path}")
        node = group[name]
        if isinstance(node, h5py.Group):
            hint = str(cls.__annotations__.get(name, ""))  # e.g. "Particles"
            values.append(_read_tree(node, _class_of(node, hint, sub, path), sub, path,
                                     allow_downcast))
        else:
            values.append(_read_array(node, allow_downcast))
    return cls(*values)


def open_hdf5(path):
    """Open ``path`` for reading: ``FileNotFoundError`` if it is missing,
    :class:`CorruptFileError` (an ``InputError``) if it is not HDF5."""
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise CorruptFileError(f"cannot open {path} as HDF5: {e}") from None


def _load(path, parts=("state", "params", "config", "history", "attrs"), numpy=False,
          allow_downcast=False) -> RunData:
    path = pathlib.Path(path)
    f = open_hdf5(path)
    out = dict.fromkeys(RunData._fields)
    try:
        with f:
            version = _to_py(f.attrs.get("format_version", FORMAT_VERSION))
            if int(version) > FORMAT_VERSION:
                raise CorruptFileError(
                    f"{path} has format_version {version}, newer than supported {FORMAT_VERSION}")
            for name, default in (("state", "State"), ("params", "Params")):
                if name in parts and name in f:
                    out[name] = _read_tree(f[name], _class_of(f[name], default, name, path),
                                           name, path, allow_downcast)
            if "config" in parts and "config" in f:
                g = f["config"]
                cls = _class_of(g, "Config", "config", path)
                fields = _read_attrs(g.attrs)
                if cls.__name__ == "Config" and "dim" not in fields:
                    raise CorruptFileError(f"config in {path} has no 'dim' (2 or 3)")
                try:
                    out["config"] = cls(**fields)
                except (TypeError, ValueError) as e:
                    raise CorruptFileError(f"config in {path} is invalid: {e}") from None
            if "history" in parts and "history" in f:
                out["history"] = _read_history(f["history"], numpy, allow_downcast)
            if "attrs" in parts:
                user = _read_attrs(f.attrs, skip=_RESERVED_ROOT_ATTRS, tuples=False)
                if "attrs" in f:
                    user.update(_read_attr_tree(f["attrs"]))
                out["attrs"] = user or None
    except (CorruptFileError, PrecisionError):
        raise
    except (OSError, KeyError, RuntimeError, ValueError, TypeError) as e:
        raise CorruptFileError(f"cannot read {path}: {type(e).__name__}: {e}") from None
    st, cf = out["state"], out["config"]
    if st is not None and cf is not None and hasattr(st, "particles") \
            and st.particles.pos.shape[-1] != cf.dim:
        raise CorruptFileError(f"{path}: the state's positions have dimension "
                               f"{st.particles.pos.shape[-1]} but config.dim = {cf.dim}")
    return RunData(**out)


def load_run(path, *, numpy=False, allow_downcast=False) -> RunData:
    """Read everything :func:`save_run` wrote.  Arrays come back as ``jax.numpy``
    arrays with their stored dtype (float64 stays float64 when ``jax_enable_x64``
    is on; JAX narrows it to float32 otherwise); with ``numpy`` the history comes
    back as NumPy arrays, exactly as stored.  Attribute values stored as JSON
    (lists, nested lists) come back as lists; a Config's as tuples.

    Raises ``FileNotFoundError`` if ``path`` does not exist,
    :class:`CorruptFileError` if it is not HDF5, is truncated, lacks a field
    (a Config without ``dim`` included) or its state and config disagree on the
    dimension, and :class:`PrecisionError` if it holds float64 arrays while JAX
    runs in float32 (``allow_downcast=True`` rounds them instead).
    """
    return _load(path, numpy=numpy, allow_downcast=allow_downcast)


def load_state(path, *, allow_downcast=False):
    """The ``State`` saved in ``path``; ``CorruptFileError`` if there is none."""
    state = _load(path, parts=("state",), allow_downcast=allow_downcast).state
    if state is None:
        raise CorruptFileError(f"state missing in {path}")
    return state


def load_history(path, *, allow_downcast=False) -> dict:
    """The history dict saved in ``path`` (``{}`` if none was saved)."""
    return _load(path, parts=("history",), allow_downcast=allow_downcast).history or {}
