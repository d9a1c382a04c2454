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


_COEFFS = {(n, d): _series_coefficients(n, d) for n in range(N_MAX + 1) for d in range(3)}


def _horner(coeffs: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.full_like(x, coeffs[-1])
    for c in coeffs[-2::-1]:
        out = out * x + c
    return out


def f_table(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """f_n(x), f_n'(x), f_n''(x) for n = 0..4, each returned with a leading axis of size 5.

    x >= 0 of any shape.  Accurate to a few ulps for all x (series below SERIES_X).
    """
    x = np.asarray(x, dtype=np.float64)
    f = np.empty((N_MAX + 1,) + x.shape)
    d1 = np.empty_like(f)
    d2 = np.empty_like(f)
    small = x < SERIES_X
    if np.any(small):
        xs = x[small]
        for n in range(N_MAX + 1):
            f[n][small] = _horner(_COEFFS[(n, 0)], xs)
            d1[n][small] = _horner(_COEFFS[(n, 1)], xs)
            d2[n][small] = _horner(_COEFFS[(n, 2)], xs)
    large = ~small
    if np.any(large):
        xl = x[large]
        th = np.sqrt(xl)
        fl = [np.cos(th), np.sin(th) / th]
        for n in range(2, N_MAX + 1):
            fl.append((1.0 / factorial(n - 2) - fl[n - 2]) / xl)
        d1l = [-0.5 * fl[1]]
        for n in range(1, N_MAX + 1):
            d1l.append((fl[n - 1] - n * fl[n]) / (2.0 * xl))
        # f_0'' from f_0' = -f_1 / 2
        d2l = [-0.5 * d1l[1]]
        for n in range(1, N_MAX + 1):
            d2l.append((d1l[n - 1] - (n + 2) * d1l[n]) / (2.0 * xl))
        for n in range(N_MAX + 1):
            f[n][large] = fl[n]
            d1[n][large] = d1l[n]
            d2[n][large] = d2l[n]
    return f, d1, d2


def c_table(t: np.ndarray, z: np.ndarray):
    """c_n(t, z), dc_n/dz, d^2c_n/dz^2 for n = 0..4, leading axis of size 5.

    c_n(t, z) = t^n f_n(z t^2): the coefficients of exp(t [w]x) and of its integrals in t.
    """
    t = np.asarray(t, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    t2 = t * t
    f, d1, d2 = f_table(z * t2)
    n = np.arange(N_MAX + 1).reshape((-1,) + (1,) * t.ndim)
    tn = t[None] ** n
    c = tn * f
    dc = tn * t2 * d1
    ddc = tn * t2 * t2 * d2
    return c, dc, ddc
