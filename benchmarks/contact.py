"""Speed and accuracy of the FFT contact solver (stages.sim.contact).

Run: python benchmarks/contact.py [--quick]   (about a minute on a 2-core CPU; --quick skips n = 256)

Scenes per grid size n: "pad", a Hertz sphere (R = 5 mm, depth 1 mm) on the 20 x 20 mm sim
pad (half-space), the contact covering ~5% of the grid as for real indenters; "pad4", the same
on the 4 mm layer of the sim pad (no Hertz reference: the layer is ~2x stiffer); "wide", the
sphere on an 8 x 8 mm grid so the contact covers ~25% of it (worst case for the iterations).
Columns: single frame, batched, full-stick shear (shift 0.1 mm), Coulomb shear (mu = 0.5).
Batched = 15 frames (3 positions x 5 depths, 0.2..1.0 mm) through solve_contact_batch.
The dense baseline builds the full 64^2 x 64^2 Boussinesq matrix and solves the contact by an
active set with Cholesky solves; it uses the same element kernel, so its answer must match.
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np                                                     # noqa: E402
from scipy import linalg                                               # noqa: E402

from benchmarks.summary import record                                  # noqa: E402
from stages.sim.contact import solve_contact, solve_contact_batch      # noqa: E402
from stages.sim.kernels import unit_kernels                            # noqa: E402

E, NU, R, DEPTH = 1.45e5, 0.45, 5.0, 1.0
E_STAR = E / (1 - NU ** 2)


def scene(n, width, centre=(0.0, 0.0)):
    h = width / n
    x = (np.arange(n) - (n - 1) / 2) * h
    xx, yy = np.meshgrid(x, x)
    return h, ((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (2 * R)


def hertz_force(d):
    return 4 / 3 * E_STAR * np.sqrt(R) * d ** 1.5 * 1e-6


def best_ms(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def dense_matrix(n, h):
    """Full (n^2, n^2) influence matrix of the same element kernel, mm per Pa."""
    k = unit_kernels((n, n), NU, None)["zz"] * (h / E)
    iy, ix = np.divmod(np.arange(n * n), n)
    return k[(iy[:, None] - iy[None, :]) + n - 1, (ix[:, None] - ix[None, :]) + n - 1]


def dense_solve(K, height, depth):
    """Active-set (Cholesky) solution of the normal contact on a dense influence matrix."""
    n = height.shape[0]
    gap = (height - depth).ravel()
    active = gap < 0
    p = np.zeros(n * n)
    for _ in range(200):
        idx = np.flatnonzero(active)
        p[:] = 0.0
        p[idx] = linalg.solve(K[np.ix_(idx, idx)], -gap[idx], assume_a="pos")
        if (p[idx] < 0).any():
            active[idx[p[idx] < 0]] = False                              # drop tensile points
            continue
        g = K @ p + gap
        enter = ~active & (g < -1e-9 * depth)
        if not enter.any():
            break
        active |= enter                                                  # add penetrating points
    return p.reshape(n, n)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="grids 64 and 128 only")
    args = ap.parse_args()
    print(f"contact benchmark: sphere R={R} mm, depth {DEPTH} mm, E={E:.3g} Pa, nu={NU}, "
          f"{os.cpu_count()} CPU(s)")
    print(f"{'n':>5} {'scene':>5} {'contact px':>10} {'single ms':>10} {'batch ms/frame':>15} "
          f"{'shear ms':>9} {'mu ms':>7} {'Hertz rel err':>14}")
    for n in ((64, 128) if args.quick else (64, 128, 256)):
        for name, width, thick in (("pad", 20.0, None), ("pad4", 20.0, 4.0), ("wide", 8.0, None)):
            h, height = scene(n, width)
            kw = dict(spacing=h, E=E, nu=NU, thickness=thick)
            res = solve_contact(height, DEPTH, **kw)                         # warms the caches
            err = (-res.force[2] - hertz_force(DEPTH)) / hertz_force(DEPTH)
            single = best_ms(lambda: solve_contact(height, DEPTH, **kw), 5)
            shear = best_ms(lambda: solve_contact(height, DEPTH, shift=(0.1, 0.0), **kw), 3)
            fric = best_ms(lambda: solve_contact(height, DEPTH, shift=(0.1, 0.0), mu=0.5, **kw), 3)
            frames = [scene(n, width, (c, 0.0))[1] for c in (-width / 5, 0.0, width / 5)
                      for _ in range(5)]
            depths = np.tile(np.linspace(0.2, 1.0, 5), 3)
            batch = best_ms(lambda: solve_contact_batch(np.stack(frames), depths, **kw),
                            1) / len(frames)
            err_txt = f"{err:+.2e}" if thick is None else "-"
            print(f"{n:>5} {name:>5} {(res.pressure > 0).sum():>10d} {single:>10.1f} "
                  f"{batch:>15.1f} {shear:>9.1f} {fric:>7.1f} {err_txt:>14}")
            if thick is None:
                record("contact", f"Hertz force rel. error, {name} {n}^2", f"{single:.1f} ms/frame", err)
    print()
    print("dense direct baseline, 64^2 grid (4096 x 4096 influence matrix, active-set Cholesky):")
    for name, width in (("pad", 20.0), ("wide", 8.0)):
        h, height = scene(64, width)
        t = time.perf_counter()
        K = dense_matrix(64, h)
        build_ms = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        p_dense = dense_solve(K, height, DEPTH)
        solve_ms = 1e3 * (time.perf_counter() - t)
        del K
        fft = solve_contact(height, DEPTH, spacing=h, E=E, nu=NU)
        fft_ms = best_ms(lambda: solve_contact(height, DEPTH, spacing=h, E=E, nu=NU), 5)
        f_dense = p_dense.sum() * h * h * 1e-6
        total = build_ms + solve_ms
        print(f"  {name:>4}: dense {total:7.1f} ms (build {build_ms:.0f} + solve {solve_ms:.0f}), "
              f"FFT {fft_ms:5.1f} ms, speed ratio {total / fft_ms:5.0f}x "
              f"(solve only {solve_ms / fft_ms:4.1f}x); |dF|/F = "
              f"{abs(-fft.force[2] - f_dense) / f_dense:.1e}, max|dp|/p_max = "
              f"{np.abs(fft.pressure - p_dense).max() / p_dense.max():.1e}")
        record("contact", f"FFT speed-up vs dense 64^2, {name}",
               f"dense {total:.0f} ms / FFT {fft_ms:.1f} ms", total / fft_ms)
        record("contact", f"  solve only, {name}", f"dense {solve_ms:.0f} ms / FFT {fft_ms:.1f} ms",
               solve_ms / fft_ms)
        record("contact", f"  |dF|/F FFT vs dense, {name}", "", abs(-fft.force[2] - f_dense) / f_dense)


if __name__ == "__main__":
    main()
