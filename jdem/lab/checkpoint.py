"""Checkpoints of a lab-test host run (:func:`jdem.lab.run`): write, and resume.

A checkpoint is a :func:`jdem.io.save_run` file (written beside its target and
renamed, so an interrupt never leaves half a file): the state and params of the
run after its last complete chunk, the config in force (capacities may have
grown), the raw records so far (the history group ``raw``, records on axis 0)
and the attribute group ``lab``: ``test``, ``record`` (records done),
``n_records``, ``record_every`` and ``status`` (``running``, ``done``,
``interrupted``).  Checkpoints of format version 1 (``raw_<name>`` history
entries and ``lab_<name>`` root attributes) still resume.  Resuming needs the
same set-up (the same test, specimen and options; a longer run is allowed) and
continues bit-for-bit.
"""
from __future__ import annotations

import numpy as np

from jdem import io
from jdem.validate import InputError


def save_checkpoint(path, setup, params, parts, record, status="running"):
    """Write the run's state after ``record`` records (``parts``: list of raw
    record dicts) to ``path``."""
    raw = {k: np.concatenate([p[k] for p in parts], axis=0) for k in parts[0]} if parts else {}
    plan = setup.plan
    lab = dict(test=plan.test.name, record=int(record), n_records=int(plan.n_records),
               record_every=int(plan.record_every), status=status)
    return io.save_run(path, state=setup.state, params=params, config=plan.config,
                       history={"raw": raw}, attrs={"lab": lab})


def load_checkpoint(path, setup):
    """``(setup, params, parts, record)`` to continue ``setup`` from the checkpoint
    at ``path``; ``InputError`` if the file belongs to another test or schedule."""
    rd = io.load_run(path)
    attrs, history = rd.attrs or {}, rd.history or {}
    if isinstance(attrs.get("lab"), dict):
        a = attrs["lab"]
        raw = {k: np.asarray(v) for k, v in history.get("raw", {}).items()}
    else:   # format version 1: prefixes in flat names
        a = {k[4:]: v for k, v in attrs.items() if k.startswith("lab_")}
        raw = {k[4:]: np.asarray(v) for k, v in history.items() if k.startswith("raw_")}
    plan = setup.plan
    if a.get("test") != plan.test.name:
        raise InputError(f"{path} is a checkpoint of {a.get('test')!r}, not of the "
                         f"{plan.test.name!r} test being resumed")
    if int(a.get("record_every", -1)) != int(plan.record_every):
        raise InputError(f"{path}: record_every = {a.get('record_every')!r} but the "
                         f"set-up has {plan.record_every!r} (resume with the set-up that wrote it)")
    if int(a["record"]) > plan.n_records:
        raise InputError(f"{path} holds {a['record']} records, more than the "
                         f"{plan.n_records} of the set-up")
    parts = [raw] if raw else []
    setup = setup.replace(state=rd.state, plan=plan.replace(config=rd.config))
    return setup, rd.params, parts, int(a["record"])
