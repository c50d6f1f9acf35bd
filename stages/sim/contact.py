"""FEM-lite contact of a rigid indenter on an elastic pad (FFT boundary elements).

Conventions: grid axis 0 is y (rows), axis 1 is x (columns); units mm, N, Pa.  `pressure` is
the compressive normal traction the indenter exerts on the pad, `traction` its shear traction
(x, y), `force` = (Fx, Fy, Fz) the force the indenter exerts on the pad in the pad frame with
z pointing out of the pad: Fz < 0 when pressing and Fx has the sign of a +x shift (the stuck
indenter drags the pad along).  `displacement` is the pad surface motion, uz < 0 into the pad.

Method.  Normal problem: displacement-controlled Polonsky-Keer conjugate gradient, with the
pressure sign constraint, on the bounding box of the region the indenter can reach (a
half-space kernel is positive, so contact never leaves {height <= depth}; a layer kernel has a
small negative rim, so the whole grid is re-solved if the box turns out too small); a cold
start is seeded from the same problem on coarser grids.  Tangential problem: the shift is
imposed as the tangential displacement of stuck points (conjugate gradient); with `mu`,
Coulomb friction |q| <= mu p is enforced by accelerated projected gradient on the convex
incremental problem, which reproduces Cattaneo-Mindlin.  Influence kernels (kernels.py) are
cached per (grid shape, nu, thickness/spacing) and scaled by spacing / E.
The two problems are solved decoupled (Goodman's approximation: the coupling scales with
1 - 2 nu for a half-space and is neglected in the solve); the reported displacement field
applies the full 3x3 influence (including coupling) to the solved tractions, so it shows the
lateral squeeze of a bonded layer.  Convolutions use 2x zero-padded rfft2 (free boundary).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from .kernels import fft_shape, kernel_spectra

_TOL = 1e-5          # residual gap / slip tolerance relative to the depth / shift
_TOL_SLIP = 1e-4     # friction stage: forces to ~1e-6, tractions to ~0.3%, 3x fewer steps
_MAX_IT = 400
_COARSEN = 48       # boxes at least this wide are seeded from a coarser grid
_ALL = ("zz", "xx", "yy", "xy", "xz", "yz")


@dataclass(frozen=True)
class ContactResult:
    pressure: np.ndarray      # (h, w) Pa, >= 0, exactly 0 outside contact
    traction: np.ndarray      # (h, w, 2) Pa, shear traction on the pad (x, y)
    displacement: np.ndarray  # (h, w, 3) mm, (ux, uy, uz), uz < 0 into the pad
    force: np.ndarray         # (3,) N, (Fx, Fy, Fz), Fz < 0 when pressing


class _Conv:
    """Linear convolution with cached unit kernels on an (m, n) grid."""

    def __init__(self, shape, nu, t_unit, comps):
        self.shape, self.big = shape, fft_shape(shape)
        self.spec = kernel_spectra(shape, nu, t_unit, comps)
        self.workers = 2 if self.big[0] * self.big[1] >= 512 * 512 else 1  # threads lose below

    def fwd(self, a):
        return sfft.rfft2(a, s=self.big, workers=self.workers)

    def inv(self, a_hat):
        m, n = self.shape
        return sfft.irfft2(a_hat, s=self.big, workers=self.workers)[:m, :n]

    def normal(self, p):
        return self.inv(self.fwd(p) * self.spec["zz"])

    def tangential(self, q):
        qx, qy = self.fwd(q[..., 0]), self.fwd(q[..., 1])
        s = self.spec
        return np.stack([self.inv(s["xx"] * qx + s["xy"] * qy),
                         self.inv(s["xy"] * qx + s["yy"] * qy)], axis=-1)


def _normal_pk(apply_k, gap0, x, active, tol, diag):
    """Polonsky-Keer conjugate gradient, displacement control: minimise 1/2 x.Kx + gap0.x
    over x >= 0 on `active` (x = 0 elsewhere).  The gap K x + gap0 must vanish where x > 0
    and be >= 0 elsewhere.  Conjugacy restarts whenever the contact set changes.
    `diag` (self-influence) sets the step when no point carries load.  Returns x, K x.
    """
    u, t, g_old, restart, err = apply_k(x), np.zeros_like(x), 1.0, True, np.inf
    for _ in range(_MAX_IT):
        g = u + gap0
        free = active & (x > 0)
        held = active & ~free
        err = max(np.abs(g[free]).max(initial=0.0), -g[held].min(initial=0.0))
        if err <= tol:
            return x, u
        gg = float((g[free] ** 2).sum())
        beta = 0.0 if restart else gg / g_old
        g_old = max(gg, 1e-300)
        t = np.where(free, g + beta * t, 0.0)
        kt = apply_k(t)
        tkt = float((t * kt).sum())
        tau = gg / tkt if tkt > 0 else 1.0 / diag
        step = x - tau * t
        # penetrating unloaded points get the same step along -gap (PK's overlap rule)
        new = np.where(active, np.maximum(np.where(held, -tau * g, step), 0.0), 0.0)
        restart = bool((new != step).any())
        u = apply_k(new) if restart else u - tau * kt
        x = new
    warnings.warn(f"normal contact solver stopped at {_MAX_IT} iterations (residual {err:.3g})",
                  RuntimeWarning, stacklevel=3)
    return x, u


def _cg(apply_k, target, active, tol):
    """Conjugate gradient for K q = target on the `active` points (q = 0 elsewhere)."""
    q = np.zeros(target.shape)
    r = np.where(active[..., None], target, 0.0)
    t, rr_old = np.zeros_like(q), 1.0
    for it in range(_MAX_IT):
        if np.sqrt((r * r).sum(-1)).max() <= tol:
            return q
        rr = float((r * r).sum())
        t = r + (0.0 if it == 0 else rr / rr_old) * t
        rr_old = rr
        kt = np.where(active[..., None], apply_k(t), 0.0)
        alpha = rr / float((t * kt).sum())
        q += alpha * t
        r -= alpha * kt
    warnings.warn("tangential stick solver did not converge", RuntimeWarning, stacklevel=4)
    return q


def _tangential(apply_k, target, active, bound, scale):
    """Shear tractions q (m, n, 2): minimise 1/2 q.Kq - target.q subject to |q_i| <= bound_i.

    Full stick (bound = inf) is the linear problem K q = target on the contact set (conjugate
    gradient).  With Coulomb friction (bound = mu p) the stick solution is projected onto the
    friction disks and refined by accelerated projected gradient (FISTA with gradient-based
    restart, step 1/L with L from a power iteration); the problem is convex, so this reaches
    the incremental Coulomb solution (Cattaneo-Mindlin from rest) without the cycling of
    stick/slip set updates near the stick edge, where the slip is tiny and its direction noise.
    """
    q = _cg(apply_k, target, active, _TOL * scale)
    mag = np.sqrt((q * q).sum(-1))
    if not (active & (mag > bound)).any():
        return q

    def proj(v):
        m = np.sqrt((v * v).sum(-1))
        v = v * np.minimum(1.0, bound / np.maximum(m, 1e-300))[..., None]
        return np.where(active[..., None], v, 0.0)

    v = np.where(active[..., None], np.ones(target.shape), 0.0)
    for _ in range(12):                               # largest eigenvalue of K on the contact
        v = np.where(active[..., None], apply_k(v), 0.0)
        lam = np.sqrt((v * v).sum())
        v /= lam
    step = 1.0 / (1.05 * lam)
    x = proj(q)
    y, tk, err = x.copy(), 1.0, np.inf
    for _ in range(5 * _MAX_IT):
        grad = apply_k(y) - target
        x_new = proj(y - step * grad)
        gmap = (y - x_new) / step                    # gradient mapping: zero at the optimum
        err = np.sqrt((gmap * gmap).sum(-1)).max()
        if err <= _TOL_SLIP * scale:
            return x_new
        t_new = 0.5 * (1 + np.sqrt(1 + 4 * tk * tk))
        if float(((y - x_new) * (x_new - x)).sum()) > 0:   # momentum points uphill: restart
            t_new, tk = 1.0, 1.0
        y = x_new + ((tk - 1) / t_new) * (x_new - x)
        x, tk = x_new, t_new
    warnings.warn(f"tangential contact solver did not converge (residual {err:.3g})",
                  RuntimeWarning, stacklevel=3)
    return x


def _normal(gap0, mask, depth, nu, t_unit, x0, tol):
    """Normal pressure (unit modulus) on a box; a cold start is seeded from the same problem
    on a grid twice as coarse (recursively), which finds the contact set in few cheap steps."""
    conv = _Conv(gap0.shape, nu, t_unit, ("zz",))
    if x0 is None or not (x0 > 0).any():
        if min(gap0.shape) >= _COARSEN:
            m, n = gap0.shape
            pad = ((0, m % 2), (0, n % 2))
            g = np.pad(np.where(mask, gap0, np.nan), pad, constant_values=np.nan)
            g = g.reshape(g.shape[0] // 2, 2, g.shape[1] // 2, 2)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)       # all-NaN blocks
                gc = np.nanmean(g, axis=(1, 3))
            mc = np.isfinite(gc)
            xc = _normal(np.where(mc, gc, gap0.max()), mc, depth, nu,
                         None if t_unit is None else t_unit / 2, None, 10 * tol)
            x0 = 0.5 * np.repeat(np.repeat(xc, 2, 0), 2, 1)[:m, :n]  # x = p * spacing / E
            x0 = np.where(mask & (gap0 < 0), x0, 0.0)
        else:
            x0 = np.where(mask & (gap0 < 0), -gap0, 0.0)     # interference, optimally scaled
            x0 *= float((x0 * x0).sum()) / max(float((x0 * conv.normal(x0)).sum()), 1e-300)
    return _normal_pk(conv.normal, gap0, x0, mask, tol, conv.spec["self_zz"])[0]


def _crop(region, shape, margin=2, step=16):
    """Bounding box of `region` with a margin, sizes rounded up to `step` (few kernel shapes)."""
    rows, cols = np.flatnonzero(region.any(1)), np.flatnonzero(region.any(0))
    box = []
    for idx, size in ((rows, shape[0]), (cols, shape[1])):
        lo, hi = max(idx[0] - margin, 0), min(idx[-1] + 1 + margin, size)
        n = min(-(-(hi - lo) // step) * step, size)
        lo = min(lo, size - n)
        box.append(slice(lo, lo + n))
    return tuple(box)


def _frame(height, depth, shift, slip0, spacing, nu, t_unit, mu, warm):
    """One frame in unit-modulus variables (pressure * spacing / E, in mm).

    Returns scaled pressure (h, w), scaled traction (h, w, 2), the tangential displacement
    from the traction alone (h, w, 2) and the full displacement (h, w, 3) in mm.
    """
    shape = height.shape
    mask = np.isfinite(height)
    gap0 = np.where(mask, height - depth, 1e6 * (1.0 + abs(depth)))  # finite: 0 * gap stays 0
    p = np.zeros(shape)
    q = np.zeros(shape + (2,))
    reach = mask & (gap0 < 0)
    full = _Conv(shape, nu, t_unit, _ALL)            # first: crops slice its kernel table
    if depth > 0 and reach.any():
        box, seed = _crop(reach, shape), None
        if warm is not None:                        # previous frame, if it overlaps this one
            seed = np.where(reach, warm, 0.0)
            seed = seed if (seed > 0).sum() >= 0.5 * (warm > 0).sum() else None
        while True:
            pb = _normal(gap0[box], mask[box], depth, nu, t_unit,
                         None if seed is None else seed[box], _TOL * depth)
            p[:] = 0.0
            p[box] = pb
            if full.spec["min_zz"] >= 0 or \
                    box == (slice(0, shape[0]), slice(0, shape[1])):
                break
            w_full = full.normal(p)                      # a layer's rim may lift the pad
            outside = np.ones(shape, bool)
            outside[box] = False
            if not (mask & outside & (w_full + gap0 < -_TOL * depth)).any():
                break
            box, seed = (slice(0, shape[0]), slice(0, shape[1])), p.copy()
        contact = p > 0
        target = np.asarray(shift, float) - (0.0 if slip0 is None else slip0)
        target = np.where(contact[..., None], np.broadcast_to(target, shape + (2,)), 0.0)
        scale = np.abs(target).max()
        if scale > 0:
            box = _crop(contact, shape)                  # the shear problem lives on the contact
            conv = _Conv((box[0].stop - box[0].start, box[1].stop - box[1].start), nu, t_unit,
                         ("xx", "yy", "xy"))
            bound = np.full(shape, np.inf) if mu is None else mu * p
            q[box] = _tangential(conv.tangential, target[box], contact[box], bound[box], scale)
    s = full.spec
    p_hat = full.fwd(p)
    disp = np.zeros(shape + (3,))
    ut = np.zeros(shape + (2,))
    if q.any():
        qx, qy = full.fwd(q[..., 0]), full.fwd(q[..., 1])
        ut = np.stack([full.inv(s["xx"] * qx + s["xy"] * qy),
                       full.inv(s["xy"] * qx + s["yy"] * qy)], -1)
        disp[..., 2] = full.inv(s["xz"] * qx + s["yz"] * qy - s["zz"] * p_hat)
    elif p.any():
        disp[..., 2] = -full.inv(s["zz"] * p_hat)
    if p.any():
        disp[..., 0] = ut[..., 0] + full.inv(s["xz"] * p_hat)
        disp[..., 1] = ut[..., 1] + full.inv(s["yz"] * p_hat)
    return p, q, ut, disp


def _pack(p, q, disp, spacing, E):
    pressure = p * (E / spacing)
    traction = q * (E / spacing)
    area = spacing * spacing * 1e-6                                  # mm^2 -> m^2
    force = np.array([traction[..., 0].sum() * area, traction[..., 1].sum() * area,
                      0.0 - pressure.sum() * area])
    return pressure, traction, disp, force


def _t_unit(thickness, spacing):
    return None if thickness is None else float(thickness) / float(spacing)


def solve_contact(height, depth, *, spacing, E, nu, thickness=None, shift=(0.0, 0.0), mu=None):
    """Solve one frame: rigid indenter `height` (mm above its lowest point, NaN/inf = absent)
    pressed `depth` mm into the pad, then moved laterally by `shift` (mm, (x, y)).

    thickness: elastic layer on a rigid base (mm), None = half-space.  mu: Coulomb friction
    coefficient, None = full stick.  A curved pad is modelled by adding its initial gap to
    `height`.  Returns a ContactResult (see module docstring for signs).
    """
    height = np.asarray(height, float)
    p, q, _, disp = _frame(height, float(depth), shift, None, float(spacing), float(nu),
                           _t_unit(thickness, spacing), mu, None)
    return ContactResult(*_pack(p, q, disp, float(spacing), float(E)))


def _stack(frames):
    return ContactResult(*(np.stack(f) for f in zip(*frames)))


def solve_contact_batch(heights, depths, *, spacing, E, nu, thickness=None, shifts=None, mu=None):
    """Independent frames (each pressed from rest) over a leading axis; each frame warm-starts
    the pressure iteration from the previous one.  Returns a ContactResult with a frame axis."""
    heights = np.asarray(heights, float)
    n = heights.shape[0]
    depths = np.broadcast_to(np.asarray(depths, float), (n,))
    shifts = np.broadcast_to(np.asarray(0.0 if shifts is None else shifts, float), (n, 2))
    t_unit, out, warm = _t_unit(thickness, spacing), [], None
    for k in range(n):
        p, q, _, disp = _frame(heights[k], float(depths[k]), shifts[k], None, float(spacing),
                               float(nu), t_unit, mu, warm)
        warm = p if p.any() else warm
        out.append(_pack(p, q, disp, float(spacing), float(E)))
    return _stack(out)


def solve_sequence(heights, depths, shifts, phases, *, spacing, E, nu, thickness=None, mu=None,
                   hysteresis=0.0):
    """A contact sequence (press, shear out, shear back, release) with memory and hysteresis.

    heights (N, h, w) or (h, w), depths (N,), shifts (N, 2) mm, phases (N,) int8 with
    0 press, 1 shear out, 2 shear back, 3 release.
    Friction memory: the accumulated slip of each pad point is carried between frames, so
    stuck points keep their offset to the indenter and shear-back under friction differs from
    shear-out (incremental Coulomb, backward Euler).  Points leaving contact are released and
    re-stick where they touch down again.
    Hysteresis: the elastomer is modelled as softer while unloading, E_unload = E (1 - h) for
    frames whose depth decreases or whose phase is release (3).  The contact geometry does not
    depend on E, so at equal depth F_unload = (1 - h) F_load; h = 0 gives identical curves.
    """
    if not 0.0 <= hysteresis < 1.0:
        raise ValueError("hysteresis must lie in [0, 1)")
    depths = np.asarray(depths, float)
    n = depths.shape[0]
    heights = np.asarray(heights, float)
    if heights.ndim == 2:
        heights = np.broadcast_to(heights, (n,) + heights.shape)
    shifts = np.broadcast_to(np.asarray(shifts, float), (n, 2))
    phases = np.asarray(phases, np.int8)
    t_unit, out, warm, slip = _t_unit(thickness, spacing), [], None, None
    for k in range(n):
        unloading = phases[k] == 3 or (k > 0 and depths[k] < depths[k - 1] - 1e-12)
        e_k = float(E) * (1.0 - hysteresis) if unloading else float(E)
        p, q, ut, disp = _frame(heights[k], float(depths[k]), shifts[k], slip, float(spacing),
                                float(nu), t_unit, mu, warm)
        slip = shifts[k] - ut               # indenter position relative to each pad point
        warm = p if p.any() else warm       # unit pressures do not depend on E: warm start holds
        out.append(_pack(p, q, disp, float(spacing), e_k))
    return _stack(out)
