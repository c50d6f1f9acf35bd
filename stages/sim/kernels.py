"""Surface influence kernels for the FFT boundary-element contact solver.

Unit system: grid step 1, Young's modulus 1. A physical kernel is the unit kernel times
spacing / E (mm per Pa, distances in grid steps), so one cache entry serves every modulus
and spacing with the same thickness/spacing ratio.

Component names, all "displacement at a field element per unit uniform traction on a source
element", offset = field - source, axis 0 = y (rows), axis 1 = x (columns):
  zz  uz INTO the body from pressure p (positive; the solver's normal operator)
  xx, yy, xy  tangential (Cerruti) ux/uy from shear tractions qx/qy
  xz, yz  ux/uy from pressure p; by Betti reciprocity also uz (OUT of the body) from qx/qy

Half-space parts are exact integrals of the Boussinesq-Cerruti point solutions over a
square element (Love's rectangle formulas).  A finite layer bonded to a rigid base adds a
smooth correction obtained from the exact Fourier-domain layer compliances (checked against
a direct solution of the Navier equations for one Fourier mode):
  normal        2/(E* q) * ((3-4v) sinh 2u - 2u) / D
  longitudinal  2/(E* q) * ((3-4v) sinh 2u + 2u) / D
  transverse    tanh(u) / (G q)
  coupling      ((1-2v)(3-4v)(cosh 2u - 1) - 2u^2) / D / (2 G q)
  D = (3-4v) cosh 2u + 2u^2 + 5 - 12v + 8v^2,   u = q * thickness.
Each factor minus its half-space limit decays like exp(-2u), so its Hankel transform is a
bounded smooth function of r/thickness; it tends to zero as thickness -> inf and makes the
layer stiffer (the correction to the normal compliance is negative: S_N < 1 for all u).
"""
from __future__ import annotations

import functools
from collections import OrderedDict

import numpy as np
import scipy.fft as sfft
from scipy import special

_U_MAX = 18.0     # (layer factor - 1) ~ u^2 exp(-2u) < 1e-13 beyond this
_N_U = 3601       # Simpson nodes on [0, _U_MAX]: step 0.005
_RHO_C = 50.0     # tabulate r/thickness up to here, asymptotic series beyond
_D_RHO = 0.02
_GAUSS = (np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)]) / 2.0, np.array([5.0, 8.0, 5.0]) / 18.0)


def _corner_sum(f, x, y):
    """Integral over the unit element centred at offset (x, y) from an antiderivative f."""
    return f(x + 0.5, y + 0.5) - f(x + 0.5, y - 0.5) - f(x - 0.5, y + 0.5) + f(x - 0.5, y - 0.5)


# Antiderivatives F with d2F/dxdy = integrand.  Corners sit at half-integers, never at 0.
def _f_inv_r(x, y):       # 1/r
    return x * np.arcsinh(y / np.abs(x)) + y * np.arcsinh(x / np.abs(y))


def _f_xx(x, y):          # x^2/r^3
    return y * np.arcsinh(x / np.abs(y))


def _f_yy(x, y):          # y^2/r^3
    return x * np.arcsinh(y / np.abs(x))


def _f_xy(x, y):          # xy/r^3
    return -np.hypot(x, y)


def _f_x(x, y):           # x/r^2
    return x * np.arctan(y / x) + 0.5 * y * np.log(x * x + y * y)


def _f_y(x, y):           # y/r^2
    return _f_x(y, x)


def _layer_factors(u, nu):
    """Layer compliance factors minus their half-space limits (all -> 0 as u -> inf)."""
    k = 3.0 - 4.0 * nu
    den = k * np.cosh(2 * u) + 2 * u * u + 5 - 12 * nu + 8 * nu * nu
    return {
        "N": (k * np.sinh(2 * u) - 2 * u) / den - 1.0,
        "L": (k * np.sinh(2 * u) + 2 * u) / den - 1.0,
        "T": np.tanh(u) - 1.0,
        "C": ((1 - 2 * nu) * k * (np.cosh(2 * u) - 1) - 2 * u * u) / den - (1 - 2 * nu),
    }


# (factor, Bessel order) pairs whose Hankel integrals g(rho) = int_0^inf f(u) J_n(u rho) du
_TRANSFORMS = (("N", 0), ("L", 0), ("T", 0), ("L", 2), ("T", 2), ("C", 1))


@functools.lru_cache(maxsize=8)
def _layer_tables(nu: float):
    """Tabulated g(rho) for rho <= _RHO_C and far-field series coefficients."""
    u = np.linspace(0.0, _U_MAX, _N_U)
    w = np.full(_N_U, 2.0)
    w[1::2] = 4.0
    w[0] = w[-1] = 1.0
    w *= (u[1] - u[0]) / 3.0                        # Simpson weights
    f = _layer_factors(u, nu)
    rho = np.arange(0.0, _RHO_C + _D_RHO / 2, _D_RHO)
    tables = {key: np.empty_like(rho) for key in _TRANSFORMS}
    for s in range(0, rho.size, 256):               # chunks keep the Bessel matrix small
        arg = np.outer(rho[s:s + 256], u)
        j0, j1 = special.j0(arg), special.j1(arg)
        safe = np.where(arg > 1e-3, arg, 1.0)
        # J2 by recurrence (special.jv is ~10x slower); series below 1e-3 avoids cancellation
        j2 = np.where(arg > 1e-3, 2 * j1 / safe - j0, arg * arg / 8)
        bessel = {0: j0, 1: j1, 2: j2}
        for (name, order) in _TRANSFORMS:
            tables[(name, order)][s:s + 256] = bessel[order] @ (f[name] * w)
    # derivatives at u=0 for the large-rho series, from
    # int_0^inf t^m J_n(t) dt = 2^m Gamma((n+m+1)/2) / Gamma((n-m+1)/2)
    us = np.linspace(0.0, 0.04, 41)
    fs = _layer_factors(us, nu)
    derivs = {}
    for name in "NLTC":
        c = np.polynomial.polynomial.polyfit(us, fs[name], 7)
        derivs[name] = (c[0], c[1], 2 * c[2], 6 * c[3])
    return rho, tables, derivs


def _hankel(nu, name, order, rho):
    grid, tables, derivs = _layer_tables(nu)
    out = np.interp(np.minimum(rho, _RHO_C), grid, tables[(name, order)])
    far = rho > _RHO_C
    if far.any():
        r = rho[far]
        f0, f1, f2, f3 = derivs[name]
        if order == 0:
            out[far] = f0 / r - f2 / (2 * r ** 3)
        elif order == 1:
            out[far] = f0 / r + f1 / r ** 2 - f3 / (2 * r ** 4)
        else:
            out[far] = f0 / r + 2 * f1 / r ** 2 + 1.5 * f2 / r ** 3
    return out


def _layer_correction(x, y, nu, t_unit):
    """Point-load layer corrections at offsets (x, y), unit spacing, E = 1."""
    r = np.hypot(x, y)
    rho = r / t_unit
    rs = np.where(r > 0, r, 1.0)
    c2, s2 = (x * x - y * y) / rs ** 2, 2 * x * y / rs ** 2
    a = 1.0 / (2 * np.pi * t_unit)
    h0 = a * ((1 - nu * nu) * _hankel(nu, "L", 0, rho) + (1 + nu) * _hankel(nu, "T", 0, rho))
    h2 = a * ((1 - nu * nu) * _hankel(nu, "L", 2, rho) - (1 + nu) * _hankel(nu, "T", 2, rho))
    h1 = a * (1 + nu) * _hankel(nu, "C", 1, rho)
    return {
        "zz": 2 * a * (1 - nu * nu) * _hankel(nu, "N", 0, rho),
        "xx": h0 - c2 * h2, "yy": h0 + c2 * h2, "xy": -s2 * h2,
        "xz": -(x / rs) * h1, "yz": -(y / rs) * h1,
    }


def _base_kernels(size: int, nu: float, t_unit: float | None) -> dict:
    """Unit kernels over all offsets |dy|, |dx| < size: arrays (2 size - 1,) * 2, centre = 0."""
    y, x = np.meshgrid(np.arange(1 - size, size, dtype=float),
                       np.arange(1 - size, size, dtype=float), indexing="ij")
    inv_r = _corner_sum(_f_inv_r, x, y)
    g = (1 + nu) / np.pi                               # 1/(2 pi G) with E = 1
    c = (1 + nu) * (1 - 2 * nu) / (2 * np.pi)          # Boussinesq-Cerruti coupling
    k = {
        "zz": (1 - nu * nu) / np.pi * inv_r,
        "xx": g * ((1 - nu) * inv_r + nu * _corner_sum(_f_xx, x, y)),
        "yy": g * ((1 - nu) * inv_r + nu * _corner_sum(_f_yy, x, y)),
        "xy": g * nu * _corner_sum(_f_xy, x, y),
        "xz": -c * _corner_sum(_f_x, x, y),
        "yz": -c * _corner_sum(_f_y, x, y),
    }
    if t_unit is not None:
        pts, wts = _GAUSS                              # 3x3 Gauss average over the element
        for py, wy in zip(pts, wts):
            for px, wx in zip(pts, wts):
                corr = _layer_correction(x + px, y + py, nu, t_unit)
                for key in k:
                    k[key] += wy * wx * corr[key]
    for arr in k.values():
        arr.setflags(write=False)
    return k


_BASES: "OrderedDict[tuple, dict]" = OrderedDict()   # (nu, t_unit) -> largest table so far


def unit_kernels(shape: tuple, nu: float, t_unit: float | None) -> dict:
    """Spatial unit kernels over all offsets of an (m, n) grid: arrays (2m-1, 2n-1), centre = 0.

    Views into the largest table computed so far for (nu, t_unit), so the crops the solver
    works on cost nothing once the full grid's table exists.
    """
    m, n = shape
    key = (float(nu), None if t_unit is None else float(t_unit))
    base = _BASES.get(key)
    if base is None or base["size"] < max(m, n):
        size = -(-max(m, n) // 64) * 64
        base = dict(_base_kernels(size, *key), size=size)
        _BASES[key] = base
        while len(_BASES) > 8:
            _BASES.popitem(last=False)
    _BASES.move_to_end(key)
    size = base["size"]
    return {name: arr[size - m:size + m - 1, size - n:size + n - 1]
            for name, arr in base.items() if name != "size"}


def fft_shape(shape: tuple) -> tuple:
    """Zero-padded size for a linear (non-periodic) convolution over an (m, n) grid."""
    return tuple(sfft.next_fast_len(2 * s - 1, real=True) for s in shape)


@functools.lru_cache(maxsize=48)
def kernel_spectra(shape: tuple, nu: float, t_unit: float | None, comps: tuple) -> dict:
    """rfft2 of the unit kernels arranged for linear convolution on an (m, n) grid."""
    m, n = shape
    big = fft_shape(shape)
    spatial = unit_kernels(shape, nu, t_unit)
    out = {}
    for key in comps:
        wrapped = np.zeros(big)
        wrapped[:2 * m - 1, :2 * n - 1] = spatial[key]
        wrapped = np.roll(wrapped, (1 - m, 1 - n), axis=(0, 1))   # offset 0 -> index 0
        spec = sfft.rfft2(wrapped)
        spec.setflags(write=False)
        out[key] = spec
    out["min_zz"] = float(spatial["zz"].min())
    out["self_zz"] = float(spatial["zz"][m - 1, n - 1])
    return out
