"""The least-squares problem of a calibration: terms (a lab-test set-up and
its target), their residuals from a pure run, the residual function of the
internal coordinates that the solvers differentiate."""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jdem import lab
from jdem.calibrate.transform import to_value
from jdem.materials import material
from jdem.state import Params
from jdem.targets import (LossWeights, Scalar, Target, check_scalar, curve_residuals,
                          load_target, scalar_residuals)
from jdem.validate import InputError


class Term(NamedTuple):
    """One simulated test and what it is compared with: a :class:`Target` curve
    or a tuple of :class:`Scalar` figures.  With ``slow`` (the set-up
    :func:`jdem.lab.slowed` by ``factor``) the residuals are those of the
    quasi-static estimate of the curve from the two runs
    (:func:`jdem.lab.extrapolated_curve`)."""

    setup: lab.Setup
    target: object
    weights: LossWeights
    slow: lab.Setup | None = None
    factor: float = 2.0


def make_terms(setup, target, weights, *, extrapolate_rate=False, factor=2.0) -> list[Term]:
    """One :class:`Term` per set-up (a set-up or a list of them), each with its
    target checked (:func:`jdem.targets.load_target`, or :class:`Scalar` figures);
    with ``extrapolate_rate``, each also with its set-up slowed by ``factor``."""
    setups = list(setup) if isinstance(setup, (list, tuple)) else [setup]
    targets = list(target) if isinstance(target, list) else [target]
    if len(setups) != len(targets):
        raise InputError(f"{len(setups)} set-up(s) but {len(targets)} target(s): give one "
                         f"target per set-up")
    out = []
    for k, (su, t) in enumerate(zip(setups, targets)):
        if not isinstance(su, lab.Setup):
            raise InputError(f"set-up {k} must be a jdem.lab.Setup, got {type(su).__name__}")
        if isinstance(t, Scalar):
            t = (t,)
        if isinstance(t, tuple) and t and all(isinstance(x, Scalar) for x in t):
            t = tuple(check_scalar(x) for x in t)
        else:
            t = load_target(t)
        slow = lab.slowed(su, factor) if extrapolate_rate else None
        out.append(Term(su, t, weights, slow, float(factor)))
    return out


def grow_term(term: Term) -> Term:
    """``term`` with the neighbour lists of its set-up(s) grown (:func:`jdem.lab.grow`)."""
    return term._replace(setup=lab.grow(term.setup),
                         slow=None if term.slow is None else lab.grow(term.slow))


def _member_residuals(hist, term: Term):
    if isinstance(term.target, Target):
        return curve_residuals(hist["axial_strain"], hist["axial_stress"], term.target,
                               term.weights, hist.get("lateral_strain"))
    return scalar_residuals(hist, term.target)


def term_residuals(hist: dict, term: Term):
    """Residuals of one term from its pure-run history: ``(r, ok, members)``.

    ``members`` (members, n) holds each member's residuals, a diverged member's
    set to 1 (a 100 % misfit, so the solver steps back); ``ok`` (members,) flags
    the members that ran without diverging; ``r`` (n,) is the members' mean,
    what an ensemble is fitted with: the ensemble's mean curve (and mean peak
    and modulus) against the target.  The members' spread about that mean is
    not part of the loss: it would fall for parameters that make the packings
    alike (measured by experiments/heldout_losses.py) and pull the fit there; it
    goes into the intervals instead (:func:`jdem.calibrate.result.packing_covariance`)."""
    if term.setup.plan.batched:
        members = jax.vmap(lambda h: _member_residuals(h, term))(
            {k: v for k, v in hist.items() if jnp.ndim(v) >= 2})
        ok = (hist["member_first_bad_step"] < 0) & jnp.all(jnp.isfinite(members), axis=1)
        members = jnp.where(ok[:, None], members, 1.0)
        return jnp.mean(members, axis=0), ok, members
    r = _member_residuals(hist, term)
    ok = (hist["first_bad_step"] < 0) & jnp.all(jnp.isfinite(r))
    r = jnp.where(ok, r, 1.0)
    return r, ok[None], r[None]


def residual_fn(u, args, *, names, lims, terms):
    """fn(u, args) -> (residuals, aux) with args = ((setup, slow set-up or None,
    params), ...) per term: the terms' residuals (:func:`term_residuals`, an
    ensemble's the members' mean) concatenated; aux ``overflowed`` (terms,),
    ``ok`` and ``members`` (per term, as :func:`term_residuals`) and ``loss``."""
    vals = {n: to_value(u[i], *lims[n]) for i, n in enumerate(names)}
    rs, over, ok, members = [], [], [], []
    for term, (setup, slow, params) in zip(terms, args):
        prm = material(params, vals)
        hist = lab.curve(setup, prm).history
        overflowed = hist["overflowed"]
        if slow is not None:
            hist_slow = lab.curve(slow, prm).history
            hist = lab.extrapolated_history(hist, hist_slow, term.factor)
            overflowed = overflowed | hist_slow["overflowed"]
        r, good, each = term_residuals(hist, term)
        rs.append(r)
        over.append(overflowed)
        ok.append(good)
        members.append(each)
    r = jnp.concatenate(rs)
    return r, dict(overflowed=jnp.stack(over), ok=tuple(ok), members=tuple(members),
                   loss=jnp.sum(r ** 2))


def residual_problem(names, lims, terms, plist):
    """``(fn, args)`` for the solvers: ``fn(u, args)`` is :func:`residual_fn`
    bound to the names, bounds and terms as a ``jax.tree_util.Partial`` (a
    pytree, so the module-level jits of :func:`compiled_steps` see its arrays as
    traced and reuse their compilation), ``args`` the (set-up, params) pairs."""
    fn = jax.tree_util.Partial(residual_fn, names=tuple(names), lims=lims, terms=tuple(terms))
    return fn, tuple((t.setup, t.slow, p) for t, p in zip(terms, plist))


def calibration_loss(params: Params, setup, target, weights=LossWeights()):
    """Sum of squared residuals of ``params`` on one lab-test set-up against one
    target (of an ensemble's mean residuals, :func:`term_residuals`), and the pure
    run's history."""
    term = make_terms(setup, target, weights)[0]
    hist = lab.curve(setup, params).history
    r, _, _ = term_residuals(hist, term)
    return jnp.sum(r ** 2), hist


def peakless(terms, histories) -> list:
    """Messages for the terms whose fitted run peaks at its last record: the
    "peak" stress of a curve or a peak / strength target is then only the
    stress where the loading stopped, not a failure (load further: a larger
    ``max_strain``).  ``histories``: one NumPy history per term."""
    out = []
    for k, (term, hist) in enumerate(zip(terms, histories)):
        needs_peak = isinstance(term.target, Target) or any(
            t.quantity in ("peak_stress", "tensile_strength") for t in term.target)
        if not needs_peak:
            continue
        key = "tensile_strength_indirect" if "tensile_strength_indirect" in hist \
            else "axial_stress"
        stress = np.atleast_2d(np.asarray(hist[key]))
        last = [m for m in range(stress.shape[0])
                if int(np.argmax(stress[m])) == stress.shape[1] - 1]
        if last:
            out.append(f"term {k} ({term.setup.plan.test.name}): the fitted curve of member(s) "
                       f"{last} has no peak before the end of loading, so its peak is the "
                       f"stress where loading stopped; raise max_strain")
    return out


def member_blocks(terms, ok, members):
    """One :class:`jdem.calibrate.result.MemberBlock` per ensemble term (a set-up
    of several members): where its (mean) residuals lie in the residual vector of
    :func:`residual_fn`, each member's residuals and ``ok`` flags (that
    function's aux ``members`` and ``ok``, one array per term)."""
    from jdem.calibrate.result import MemberBlock

    out, start = [], 0
    for term, flags, each in zip(terms, ok, members):
        size = np.shape(each)[1]          # the length of the term's mean residuals
        if term.setup.plan.batched and term.setup.n_members > 1:
            out.append(MemberBlock(start, size, np.asarray(each), np.asarray(flags, bool)))
        start += size
    return out


def n_data(term):
    """The residuals of ``term`` that carry data (curve points or figures; an
    ensemble's are its members' mean)."""
    return len(term.target.strain) if isinstance(term.target, Target) else len(term.target)
