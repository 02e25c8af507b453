#!/usr/bin/env python3
"""Compare bfpscope's multi-bead template fit (Rust, levenberg-marquardt crate) with
scipy.optimize.least_squares on the same data (issue 4, "Speed").

The Rust benchmark (`cargo bench --bench fit`) writes, per case, the Sx/Sy images, the template
grid, the initial guesses, the ground truth and its own timing to target/fit_bench/<case>/.
This script fits the same model (eq. multiBeadFit: weighted sum of shifted templates, Sx and Sy
together) with scipy.optimize.least_squares (method 'trf', analytic Jacobian from bicubic
RectBivariateSpline interpolants of the same template grid, default tolerances 1e-8, zero
outside the template's extent as in Rust), from the same initial guesses, and reports the time
ratio and the accuracies of both against the ground truth.

Usage: python3 scripts/py/fit_compare.py [--run-bench] [--repeats N]
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.optimize import least_squares

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DIR = os.path.join(ROOT, "target", "fit_bench")


class TemplateModel:
    """Sx, Sy of the reference bead vs displacement (u, v), bicubic spline through the nodes."""

    def __init__(self, u, v, tx, ty):
        # Arrays are indexed [v, u]; RectBivariateSpline(x=v, y=u, z).
        self.sx = RectBivariateSpline(v, u, tx, kx=3, ky=3, s=0)
        self.sy = RectBivariateSpline(v, u, ty, kx=3, ky=3, s=0)
        self.ulo, self.uhi, self.vlo, self.vhi = u[0], u[-1], v[0], v[-1]

    def __call__(self, du, dv, deriv=False):
        inside = (du >= self.ulo) & (du <= self.uhi) & (dv >= self.vlo) & (dv <= self.vhi)
        out = []
        for s in (self.sx, self.sy):
            val = np.where(inside, s.ev(dv, du), 0.0)
            if deriv:
                d_u = np.where(inside, s.ev(dv, du, dy=1), 0.0)
                d_v = np.where(inside, s.ev(dv, du, dx=1), 0.0)
                out.append((val, d_u, d_v))
            else:
                out.append(val)
        return out


def fit_scipy(case):
    d = os.path.join(DIR, case)
    sx, sy = np.load(os.path.join(d, "sx.npy")), np.load(os.path.join(d, "sy.npy"))
    x, y = np.load(os.path.join(d, "x.npy")), np.load(os.path.join(d, "y.npy"))
    tm = TemplateModel(np.load(os.path.join(d, "tpl_u.npy")), np.load(os.path.join(d, "tpl_v.npy")),
                       np.load(os.path.join(d, "tpl_sx.npy")), np.load(os.path.join(d, "tpl_sy.npy")))
    init = np.load(os.path.join(d, "init.npy"))  # rows: weight, x, y
    xx, yy = np.meshgrid(x, y)
    xx, yy = xx.ravel(), yy.ravel()
    data = np.concatenate([sx.ravel(), sy.ravel()])

    def residuals(p):
        mx = np.zeros_like(xx)
        my = np.zeros_like(xx)
        for c, bx, by in p.reshape(-1, 3):
            tx, ty = tm(xx - bx, yy - by)
            mx += c * tx
            my += c * ty
        return np.concatenate([mx, my]) - data

    def jacobian(p):
        n = len(p) // 3
        j = np.empty((2 * xx.size, 3 * n))
        for i, (c, bx, by) in enumerate(p.reshape(-1, 3)):
            (tx, txu, txv), (ty, tyu, tyv) = tm(xx - bx, yy - by, deriv=True)
            j[:, 3 * i] = np.concatenate([tx, ty])
            j[:, 3 * i + 1] = -c * np.concatenate([txu, tyu])
            j[:, 3 * i + 2] = -c * np.concatenate([txv, tyv])
        return j

    res = least_squares(residuals, init.ravel(), jac=jacobian, method="trf")
    return res


def errors(p, truth):
    beads = p.reshape(-1, 3)
    ep, ew = 0.0, 0.0
    for w, tx, ty in truth:
        k = np.argmin(np.hypot(beads[:, 1] - tx, beads[:, 2] - ty))
        ep = max(ep, np.hypot(beads[k, 1] - tx, beads[k, 2] - ty))
        ew = max(ew, abs(beads[k, 0] / w - 1.0))
    return ep, ew


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-bench", action="store_true", help="run `cargo bench --bench fit` first")
    ap.add_argument("--repeats", type=int, default=5, help="scipy repetitions (median time)")
    a = ap.parse_args()
    if a.run_bench:
        subprocess.run(["cargo", "bench", "--bench", "fit"], cwd=ROOT, check=True)
    cases = sorted(c for c in os.listdir(DIR) if os.path.exists(os.path.join(DIR, c, "rust.json"))) if os.path.isdir(DIR) else []
    if not cases:
        sys.exit(f"no benchmark data in {DIR}: run `cargo bench --bench fit` first (or pass --run-bench)")
    report = []
    print(f"{'case':<12} {'rust ms':>9} {'it':>4} {'scipy ms':>10} {'nfev':>5} {'ratio':>7}   pos err nm (rust/scipy)   weight err % (rust/scipy)")
    for c in cases:
        rj = json.load(open(os.path.join(DIR, c, "rust.json")))
        truth = np.load(os.path.join(DIR, c, "truth.npy"))
        times = []
        res = None
        for _ in range(max(1, a.repeats)):
            t0 = time.perf_counter()
            res = fit_scipy(c)
            times.append((time.perf_counter() - t0) * 1e3)
        ms = float(np.median(times))
        ep, ew = errors(res.x, truth)
        ratio = ms / rj["rust_ms"]
        row = dict(case=c, rust_ms=rj["rust_ms"], rust_iterations=rj["iterations"], scipy_ms=ms, scipy_nfev=int(res.nfev),
                   scipy_njev=int(res.njev), ratio=ratio, rust_pos_err_nm=rj["max_pos_err_nm"], scipy_pos_err_nm=ep * 1e3,
                   rust_weight_err_pct=rj["max_weight_err_pct"], scipy_weight_err_pct=ew * 100, scipy_status=int(res.status),
                   rust_rss=rj["rss"], scipy_rss=float(2 * res.cost))
        report.append(row)
        print(f"{c:<12} {rj['rust_ms']:9.2f} {rj['iterations']:4d} {ms:10.1f} {res.nfev:5d} {ratio:6.1f}×   "
              f"{rj['max_pos_err_nm']:6.2f} / {ep * 1e3:6.2f}            {rj['max_weight_err_pct']:5.2f} / {ew * 100:5.2f}")
        print(f"{'':<12} RSS rust {rj['rss']:.6e}  scipy {2 * res.cost:.6e}")
    with open(os.path.join(DIR, "compare.json"), "w") as f:
        json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
