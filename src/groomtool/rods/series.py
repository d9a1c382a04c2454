"""The scalar functions behind every closed form of the Super-Helix, safe at w -> 0.

With theta^2 = x, define

    f_n(x) = sum_k (-x)^k / (2k + n)!      (an entire function of x)

so f_0 = cos(theta), f_1 = sin(theta)/theta, f_2 = (1 - cos theta)/theta^2,
f_3 = (theta - sin theta)/theta^3, f_4 = (theta^2/2 - 1 + cos theta)/theta^4.
They obey f_n = 1/n! - x f_{n+2} and n f_n + 2 x f_n' = f_{n-1}.

A helix element of length t and material Darboux vector omega (z = |omega|^2) uses

    c_n(t, z) = t^n f_n(z t^2) = sum_k (-z)^k t^(2k+n) / (2k+n)!

e.g. exp(t [omega]x) = I + c_1 [omega]x + c_2 [omega]x^2.  Its z-derivatives are
d c_n / dz = t^(n+2) f_n'(z t^2) and d^2 c_n / dz^2 = t^(n+4) f_n''(z t^2).

Below SERIES_X the Taylor series is summed (no cancellation, no division by a small theta);
above it the closed forms are used, with the recurrences for higher n and the derivatives.
"""

from __future__ import annotations

from math import factorial

import numpy as np
from numba import njit

SERIES_X = 4.0  # theta < 2: the series terms stay below 1 and 18 terms reach round-off
_N_TERMS = 18
N_MAX = 4


def _series_coefficients(n: int, order: int) -> np.ndarray:
    """Coefficients a_k of the order-th derivative of f_n as a power series in x."""
    k = np.arange(_N_TERMS + order)
    a = np.array([(-1.0) ** kk / factorial(2 * kk + n) for kk in k])
    for _ in range(order):
        a = a[1:] * np.arange(1, len(a))
    return a[:_N_TERMS]


# _COEFF_ARRAY[d, n] = the Taylor coefficients of the d-th derivative of f_n, (3, 5, T)
_COEFF_ARRAY = np.array([[_series_coefficients(n, d) for n in range(N_MAX + 1)] for d in range(3)])
_INV_FACT = np.array([1.0 / factorial(n) for n in range(N_MAX + 1)])


@njit(cache=True)
def _f_point(x, order, out):
    """out[d, n] = d-th derivative of f_n at x, d <= order."""
    if x < SERIES_X:
        T = _COEFF_ARRAY.shape[2]
        for d in range(order + 1):
            for n in range(N_MAX + 1):
                acc = _COEFF_ARRAY[d, n, T - 1]
                for k in range(T - 2, -1, -1):
                    acc = acc * x + _COEFF_ARRAY[d, n, k]
                out[d, n] = acc
        return
    th = np.sqrt(x)
    out[0, 0] = np.cos(th)
    out[0, 1] = np.sin(th) / th
    for n in range(2, N_MAX + 1):
        out[0, n] = (_INV_FACT[n - 2] - out[0, n - 2]) / x
    if order >= 1:
        out[1, 0] = -0.5 * out[0, 1]
        for n in range(1, N_MAX + 1):
            out[1, n] = (out[0, n - 1] - n * out[0, n]) / (2.0 * x)
    if order >= 2:
        out[2, 0] = -0.5 * out[1, 1]
        for n in range(1, N_MAX + 1):
            out[2, n] = (out[1, n - 1] - (n + 2) * out[1, n]) / (2.0 * x)


@njit(cache=True)
def _f23_point(x):
    """(f_2(x), f_3(x)), the same values as :func:`_f_point` returns for them (positions need only these)."""
    if x < SERIES_X:
        T = _COEFF_ARRAY.shape[2]
        f2 = _COEFF_ARRAY[0, 2, T - 1]
        f3 = _COEFF_ARRAY[0, 3, T - 1]
        for k in range(T - 2, -1, -1):
            f2 = f2 * x + _COEFF_ARRAY[0, 2, k]
            f3 = f3 * x + _COEFF_ARRAY[0, 3, k]
        return f2, f3
    th = np.sqrt(x)
    return (_INV_FACT[0] - np.cos(th)) / x, (_INV_FACT[1] - np.sin(th) / th) / x


@njit(cache=True)
def _c_kernel(t, z, order, out):
    """out[d, n, i] = d^d c_n / dz^d (t_i, z_i) with c_n = t^n f_n(z t^2)."""
    buf = np.empty((3, N_MAX + 1))
    for i in range(t.shape[0]):
        ti = t[i]
        t2 = ti * ti
        _f_point(z[i] * t2, order, buf)
        tn = 1.0
        for n in range(N_MAX + 1):
            scale = tn
            for d in range(order + 1):
                out[d, n, i] = scale * buf[d, n]
                scale *= t2
            tn *= ti


def c_table(t: np.ndarray, z: np.ndarray, order: int = 2):
    """c_n(t, z) and its first ``order`` z-derivatives for n = 0..4, each with a leading axis of size 5.

    c_n(t, z) = t^n f_n(z t^2): the coefficients of exp(t [w]x) and of its integrals in t.
    Returns (c, dc, ddc) with None for derivatives beyond ``order``.
    """
    t, z = np.broadcast_arrays(np.asarray(t, dtype=np.float64), np.asarray(z, dtype=np.float64))
    shape = t.shape
    out = np.empty((order + 1, N_MAX + 1, t.size))
    _c_kernel(np.ascontiguousarray(t.ravel()), np.ascontiguousarray(z.ravel()), order, out)
    out = out.reshape((order + 1, N_MAX + 1) + shape)
    tables = [out[d] for d in range(order + 1)]
    return tuple(tables + [None] * (2 - order))
