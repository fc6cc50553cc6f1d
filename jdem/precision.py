"""Working precision: the float32 / float64 switch, and positions that keep
sub-nanometre increments in float32.

Why positions need care
-----------------------
A float32 number carries 24 significant bits: a coordinate of 5 cm is held to
3.7 nm.  A platen test moves a 10 cm specimen's platens by ~1 nm per step
(2e-7 strain per step, 000 §3.3 time step), so ``x += v dt`` in plain float32
rounds every step's increment to a multiple of 3.7 nm: the platen runs 11 %
fast or stops, and overlaps (hence wall and contact forces) carry the same
error.  The forces themselves only need relative precision (bond forces are
incremental, 002 eq 3; overlaps are differences of nearby positions).

So every position is a pair ``hi + lo`` of floats of the working dtype
(compensated summation): ``Particles.pos`` / ``Walls.point`` is ``hi``, the
nearest float to the position, and ``Particles.pos_lo`` / ``Walls.point_lo``
is ``lo``, the rest (|lo| <= half an ulp of hi).  :func:`add` moves a pair by
an increment exactly (Knuth's TwoSum, then a renormalisation, FastTwoSum), so
the pair holds ~48 significant bits in float32: a 5 cm coordinate to ~1e-16 m,
far below any increment.  :func:`difference` gives the difference of two
pairs to the working dtype's relative precision of the *difference* (an
overlap, a wall gap, a displacement), not of the coordinates.

Both are plain arithmetic: they ``jit``, ``vmap`` and differentiate (the
tangent travels in ``hi``; ``lo``'s tangent is exactly 0) and cost a few flops
per particle per step.  float64 needs no pair (a 5 cm coordinate to 7e-18 m):
there :func:`add` is the plain sum and ``lo`` stays 0, so float64 runs are
bit-for-bit those of single positions.  Anything that needs a position only to the nearest float
(the neighbour search, plots, set-up) reads ``pos`` alone.

The switch
----------
``precision="float32"`` (the default of the lab tests and calibration) or
``"float64"`` (the analytic-value tests); :func:`dtype_of` turns it into a dtype
and :func:`cast` casts every floating leaf of a pytree.  float64 needs
``jax.config.update("jax_enable_x64", True)`` at start-up; without it JAX
cannot hold a float64 array, and :func:`dtype_of` says so.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jdem.validate import InputError

PRECISIONS = ("float32", "float64")
DEFAULT = "float32"     #: the lab tests' and calibration's working precision


def add(hi, lo, inc):
    """The pair ``(hi, lo)`` moved by ``inc``, as a renormalised pair ``(hi', lo')``
    with hi' + lo' = hi + lo + inc up to ~2^-48 relative (float32).  Arrays of
    one shape (or broadcastable), any float dtype; in float64 the plain sum
    (``lo`` returned as it is)."""
    s = hi + inc
    if jnp.result_type(hi) == jnp.float64:
        return s, lo
    # TwoSum (Knuth): the rounding error of s = hi + inc, exactly, for any order
    # of magnitude of hi and inc
    b = s - hi
    err = (hi - (s - b)) + (inc - b)
    lo = lo + err
    # FastTwoSum: fold lo back so that |lo| stays below half an ulp of hi
    hi_new = s + lo
    return hi_new, lo - (hi_new - s)


def difference(a_hi, a_lo, b_hi, b_lo):
    """(a_hi + a_lo) - (b_hi + b_lo), to the working precision of the result:
    ``a_hi - b_hi`` is exact when the two are within a factor 2 of each other
    (Sterbenz), which nearby positions are."""
    return (a_hi - b_hi) + (a_lo - b_lo)


def dtype_of(precision):
    """The JAX float dtype of ``precision`` ("float32" / "float64", or a dtype).
    Raises :class:`InputError` for another name, and for float64 while JAX runs
    without x64."""
    name = np.dtype(precision).name if not isinstance(precision, str) else precision
    if name not in PRECISIONS:
        raise InputError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if name == "float64" and not jax.config.read("jax_enable_x64"):
        raise InputError("precision='float64' needs JAX's float64 mode: call "
                         "jax.config.update('jax_enable_x64', True) before creating any array")
    return jnp.dtype(name)


def cast(tree, dtype):
    """``tree`` with every floating-point leaf cast to ``dtype`` (integer and
    bool leaves, and non-array leaves, as they are)."""
    dtype = jnp.dtype(dtype)

    def one(a):
        if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating) and a.dtype != dtype:
            return jnp.asarray(a, dtype)
        return a
    return jax.tree_util.tree_map(one, tree)
