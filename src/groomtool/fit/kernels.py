"""Small kernels for the fit: 3-vectors and the helix functions f1, f2, f3 (arrays; scalars for numba).

f_n(x) as in :mod:`groomtool.rods.series` (theta^2 = x), in forms without cancellation:

    f1 = sin(theta)/theta,    f2 = (1 - cos theta)/theta^2 = 2 sin^2(theta/2)/theta^2,
    f3 = (theta - sin theta)/theta^3   (Taylor series sum (-x)^k/(2k+3)! below theta = 1).

Cheaper than ``series.c_table`` at t = 1 (no derivatives), same accuracy (a few ulps).  ``*_s`` functions: the
same on scalars, for numba kernels (same operations in the same order as the array versions).
"""

from __future__ import annotations

from math import factorial

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

_F3_SERIES = np.array([(-1.0) ** k / factorial(2 * k + 3) for k in range(10)])


def dot(a, b):
    """a . b over the last axis of (..., 3) arrays."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a, b):
    """a x b over the last axis of (..., 3) arrays (faster than np.cross on large arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def norm(a):
    return np.sqrt(dot(a, a))


def f123(x):
    """(f1, f2, f3) of x = theta^2 >= 0, each of x's shape."""
    x = np.asarray(x, dtype=np.float64)
    th = np.sqrt(x)
    f1 = np.sinc(th / np.pi)
    half = np.sinc(th / (2.0 * np.pi))
    f2 = 0.5 * half * half
    small = th < 1.0
    f3 = np.empty_like(x)
    xs = x[small]
    acc = np.full_like(xs, _F3_SERIES[-1])
    for c in _F3_SERIES[-2::-1]:
        acc = acc * xs + c
    f3[small] = acc
    tl = th[~small]
    f3[~small] = (tl - np.sin(tl)) / (tl * tl * tl)
    return f1, f2, f3


@njit(cache=True, error_model="numpy")
def sinc_s(x):
    """np.sinc on a scalar: sin(pi x) / (pi x), with x = 0 replaced by 1e-20 as numpy does."""
    y = np.pi * (x if x != 0.0 else 1.0e-20)
    return np.sin(y) / y


@njit(cache=True, error_model="numpy")
def f123_s(x):
    """:func:`f123` of one x = theta^2 >= 0."""
    th = np.sqrt(x)
    f1 = sinc_s(th / np.pi)
    half = sinc_s(th / (2.0 * np.pi))
    f2 = 0.5 * half * half
    if th < 1.0:
        f3 = _F3_SERIES[-1]
        for k in range(len(_F3_SERIES) - 2, -1, -1):
            f3 = f3 * x + _F3_SERIES[k]
    else:
        f3 = (th - np.sin(th)) / (th * th * th)
    return f1, f2, f3


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c rounded once (llvm.fma.f64), in numba kernels."""
    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")
        return builder.call(fn, args)
    return types.float64(types.float64, types.float64, types.float64), codegen
