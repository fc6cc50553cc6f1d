"""Checkpoints of a lab-test host run (:func:`jdem.lab.run`): write, and resume.

A checkpoint is a :func:`jdem.io.save_run` file (written beside its target and
renamed, so an interrupt never leaves half a file): the state and params of the
run after its last complete chunk, the config in force (capacities may have
grown), the raw records so far (history entries ``raw_<name>``, records on axis
0) and root attributes ``lab_test``, ``lab_record`` (records done),
``lab_n_records``, ``lab_record_every`` and ``lab_status`` (``running``,
``done``, ``interrupted``).  Resuming needs the same set-up (the same test,
specimen and options; a longer run is allowed) and continues bit-for-bit.
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
    attrs = dict(lab_test=plan.test.name, lab_record=int(record),
                 lab_n_records=int(plan.n_records), lab_record_every=int(plan.record_every),
                 lab_status=status)
    return io.save_run(path, state=setup.state, params=params, config=plan.config,
                       history={f"raw_{k}": v for k, v in raw.items()}, attrs=attrs)


def load_checkpoint(path, setup):
    """``(setup, params, parts, record)`` to continue ``setup`` from the checkpoint
    at ``path``; ``InputError`` if the file belongs to another test or schedule."""
    rd = io.load_run(path)
    a = rd.attrs or {}
    plan = setup.plan
    if a.get("lab_test") != plan.test.name:
        raise InputError(f"{path} is a checkpoint of {a.get('lab_test')!r}, not of the "
                         f"{plan.test.name!r} test being resumed")
    if int(a.get("lab_record_every", -1)) != int(plan.record_every):
        raise InputError(f"{path}: lab_record_every = {a.get('lab_record_every')!r} but the "
                         f"set-up has {plan.record_every!r} (resume with the set-up that wrote it)")
    if int(a["lab_record"]) > plan.n_records:
        raise InputError(f"{path} holds {a['lab_record']} records, more than the "
                         f"{plan.n_records} of the set-up")
    raw = {k[4:]: np.asarray(v) for k, v in (rd.history or {}).items() if k.startswith("raw_")}
    parts = [raw] if raw else []
    setup = setup.replace(state=rd.state, plan=plan.replace(config=rd.config))
    return setup, rd.params, parts, int(a["lab_record"])
