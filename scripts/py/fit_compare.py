#!/usr/bin/env python3
"""Compare bfpscope's multi-bead template fit (Rust, levenberg-marquardt crate) with
scipy.optimize.least_squares on the same data (the fit's speed target).

The Rust benchmark (`cargo bench --features bench --bench fit`) writes, per case, the Sx/Sy images, the template
grid, the initial guesses, the ground truth and its own timing to target/fit_bench/<case>/.
This script fits the same model (eq. multiBeadFit: weighted sum of shifted templates, Sx and Sy
together) with scipy.optimize.least_squares (method 'trf', analytic Jacobian from bicubic
RectBivariateSpline interpolants of the same template grid, default tolerances 1e-8, zero
outside the template's extent as in Rust), from the same initial guesses, and reports the time
ratio and the accuracies of both against the ground truth.

Two scipy set-ups are timed, and the ratio is quoted against the faster one:
  dense   method 'trf', dense analytic Jacobian (M × 3n), tr_solver 'exact' (scipy's default);
  sparse  method 'trf', the same Jacobian as a scipy.sparse CSR matrix holding only each bead's
          window (the pixels within the template's extent around it), tr_solver 'lsmr' — what a
          scipy user would write for a field of many beads.
Accuracy is compared three ways, all printed: the largest position error (nm) and weight error
(%) of each fit against the simulated truth, the relative difference of the residual sums of
squares (both fits must reach the same minimum: |RSS_scipy/RSS_rust − 1| should be ≲ 1e-6), and
the largest difference between the two fits' positions (nm).

Scenes: the Rust bench writes them (rendered by bfpscope's simulator with detector noise, the
ground truth, the template grid and the start from bfpscope's detection) to the exchange
directory: $FIT_BENCH_DIR, else <repository>/target/fit_bench (the bench uses the same rule; it
does not follow CARGO_TARGET_DIR). The scipy model is built from the template grid alone
(its own spline), not from bfpscope's interpolant.

Usage: python3 scripts/py/fit_compare.py [--run-bench] [--repeats N] [--cases a,b] [--json FILE]
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
from scipy.sparse import csr_matrix

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DIR = os.environ.get("FIT_BENCH_DIR") or os.path.join(ROOT, "target", "fit_bench")


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


def fit_scipy(case, sparse=False):
    d = os.path.join(DIR, case)
    sx, sy = np.load(os.path.join(d, "sx.npy")), np.load(os.path.join(d, "sy.npy"))
    x, y = np.load(os.path.join(d, "x.npy")), np.load(os.path.join(d, "y.npy"))
    tm = TemplateModel(np.load(os.path.join(d, "tpl_u.npy")), np.load(os.path.join(d, "tpl_v.npy")),
                       np.load(os.path.join(d, "tpl_sx.npy")), np.load(os.path.join(d, "tpl_sy.npy")))
    init = np.load(os.path.join(d, "init.npy"))  # rows: weight (reference-bead units), x, y
    rj = json.load(open(os.path.join(d, "rust.json")))
    inv_f = 1.0 / rj.get("norm_factor", 1.0)  # template units → instrument units
    xx, yy = np.meshgrid(x, y)
    xx, yy = xx.ravel(), yy.ravel()
    data = np.concatenate([sx.ravel(), sy.ravel()])

    ulo, uhi, vlo, vhi = tm.ulo, tm.uhi, tm.vlo, tm.vhi
    npx = xx.size

    def window(bx, by):
        """Pixels within the template's extent around a bead (the template is zero outside)."""
        return np.nonzero((xx - bx >= ulo) & (xx - bx <= uhi) & (yy - by >= vlo) & (yy - by <= vhi))[0]

    def residuals(p):
        mx = np.zeros_like(xx)
        my = np.zeros_like(xx)
        for c, bx, by in p.reshape(-1, 3):
            k = window(bx, by)
            tx, ty = tm(xx[k] - bx, yy[k] - by)
            mx[k] += c * inv_f * tx
            my[k] += c * inv_f * ty
        return np.concatenate([mx, my]) - data

    def jacobian(p):
        n = len(p) // 3
        j = np.empty((2 * xx.size, 3 * n))
        for i, (c, bx, by) in enumerate(p.reshape(-1, 3)):
            (tx, txu, txv), (ty, tyu, tyv) = tm(xx - bx, yy - by, deriv=True)
            j[:, 3 * i] = inv_f * np.concatenate([tx, ty])
            j[:, 3 * i + 1] = -c * inv_f * np.concatenate([txu, tyu])
            j[:, 3 * i + 2] = -c * inv_f * np.concatenate([txv, tyv])
        return j

    def jacobian_sparse(p):
        rows, cols, vals = [], [], []
        for i, (c, bx, by) in enumerate(p.reshape(-1, 3)):
            k = window(bx, by)
            (tx, txu, txv), (ty, tyu, tyv) = tm(xx[k] - bx, yy[k] - by, deriv=True)
            r = np.concatenate([k, k + npx])
            for col, v in ((3 * i, inv_f * np.concatenate([tx, ty])),
                           (3 * i + 1, -c * inv_f * np.concatenate([txu, tyu])),
                           (3 * i + 2, -c * inv_f * np.concatenate([txv, tyv]))):
                rows.append(r)
                cols.append(np.full(r.size, col))
                vals.append(v)
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(2 * npx, p.size))

    if sparse:
        res = least_squares(residuals, init.ravel(), jac=jacobian_sparse, method="trf", tr_solver="lsmr")
    else:
        res = least_squares(residuals, init.ravel(), jac=jacobian, method="trf")
    return res


def keys_kernel(t):
    """Keys' cubic convolution kernel (a = −1/2), bfpscope's template interpolant."""
    t = np.abs(t)
    return np.where(t <= 1, 1.5 * t**3 - 2.5 * t**2 + 1,
                    np.where(t < 2, -0.5 * t**3 + 2.5 * t**2 - 4 * t + 2, 0.0))


def keys_eval(tu, tv, T, du, dv):
    """The template T (nodes tu × tv, indexed [v, u]) at displacements (du, dv) by Keys' cubic
    convolution, zero outside the node extent and nodes outside the grid counted as zero —
    written here independently of bfpscope's Rust code."""
    h = tu[1] - tu[0]
    fu, fv = (du - tu[0]) / h, (dv - tv[0]) / h
    inside = (du >= tu[0]) & (du <= tu[-1]) & (dv >= tv[0]) & (dv <= tv[-1])
    iu = np.clip(np.floor(fu).astype(int), 0, len(tu) - 2)
    iv = np.clip(np.floor(fv).astype(int), 0, len(tv) - 2)
    out = np.zeros_like(du, dtype=float)
    for b in range(-1, 3):
        for a in range(-1, 3):
            ju, jv = iu + a, iv + b
            ok = (ju >= 0) & (ju < len(tu)) & (jv >= 0) & (jv < len(tv))
            val = np.where(ok, T[np.clip(jv, 0, len(tv) - 1), np.clip(ju, 0, len(tu) - 1)], 0.0)
            out += keys_kernel(fu - ju) * keys_kernel(fv - jv) * val
    return np.where(inside, out, 0.0)


def interpolant_check(case, rust_p):
    """RSS at bfpscope's fitted parameters of (a) the template interpolated by Keys' cubic (an
    independent numpy version of bfpscope's model) and (b) scipy's bicubic spline, each relative
    to bfpscope's RSS: (a) ≈ 0 confirms bfpscope's minimum; (b) is how much of scipy's RSS
    difference comes from its interpolant alone."""
    d = os.path.join(DIR, case)
    L = lambda n: np.load(os.path.join(d, n))
    sx, sy, x, y = L("sx.npy"), L("sy.npy"), L("x.npy"), L("y.npy")
    tu, tv = L("tpl_u.npy"), L("tpl_v.npy")
    tpl = (L("tpl_sx.npy"), L("tpl_sy.npy"))
    rj = json.load(open(os.path.join(d, "rust.json")))
    inv_f = 1.0 / rj.get("norm_factor", 1.0)
    tm = TemplateModel(tu, tv, *tpl)
    xx, yy = np.meshgrid(x, y)
    out = {}
    for name in ("keys", "spline"):
        rss = 0.0
        for ch, data in enumerate((sx, sy)):
            m = np.zeros_like(xx)
            for c, bx, by in rust_p.reshape(-1, 3):
                if name == "keys":
                    m += c * inv_f * keys_eval(tu, tv, tpl[ch], xx - bx, yy - by)
                else:
                    m += c * inv_f * tm(xx - bx, yy - by)[ch]
            rss += float(np.sum((m - data) ** 2))
        out[name] = rss / rj["rss"] - 1.0
    return out


def errors(p, truth):
    beads = p.reshape(-1, 3)
    ep, ew = 0.0, 0.0
    for w, tx, ty in truth:
        k = np.argmin(np.hypot(beads[:, 1] - tx, beads[:, 2] - ty))
        ep = max(ep, np.hypot(beads[k, 1] - tx, beads[k, 2] - ty))
        ew = max(ew, abs(beads[k, 0] / w - 1.0))
    return ep, ew


def timed(case, sparse, repeats):
    """Median wall time (ms) of `repeats` fits (one only when a fit takes over 10 s)."""
    times, res = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = fit_scipy(case, sparse=sparse)
        times.append((time.perf_counter() - t0) * 1e3)
        if times[-1] > 10e3:
            break
    return float(np.median(times)), res, len(times)


def max_pos_diff(p, q):
    """Largest distance (µm) from a bead of fit p to the nearest bead of fit q."""
    a, b = p.reshape(-1, 3), q.reshape(-1, 3)
    return max(float(np.min(np.hypot(b[:, 1] - w[1], b[:, 2] - w[2]))) for w in a)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-bench", action="store_true", help="run `cargo bench --features bench --bench fit` first")
    ap.add_argument("--repeats", type=int, default=3, help="scipy repetitions (median time)")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all found)")
    ap.add_argument("--json", default="", help="also write the report to this file")
    a = ap.parse_args()
    if a.run_bench:
        subprocess.run(["cargo", "bench", "--bench", "fit"], cwd=ROOT, check=True)
    cases = sorted(c for c in os.listdir(DIR) if os.path.exists(os.path.join(DIR, c, "rust.json"))) if os.path.isdir(DIR) else []
    if a.cases:
        cases = [c for c in cases if c in a.cases.split(",")]
    if not cases:
        sys.exit(f"no benchmark data in {DIR}: run `cargo bench --features bench --bench fit` first (or pass --run-bench)")
    report = []
    for c in cases:
        rj = json.load(open(os.path.join(DIR, c, "rust.json")))
        truth = np.load(os.path.join(DIR, c, "truth.npy"))
        rust_p = np.load(os.path.join(DIR, c, "fit.npy")).ravel()
        row = dict(case=c, beads=int(rj["beads"]), pixels=rj["pixels"], rust_ms=rj["rust_ms"],
                   rust_iterations=rj["iterations"], rust_pos_err_nm=rj["max_pos_err_nm"],
                   rust_weight_err_pct=rj["max_weight_err_pct"], rust_rss=rj["rss"])
        print(f"{c}: bfpscope {rj['rust_ms']:.2f} ms, {rj['iterations']} iterations; "
              f"max errors vs truth {rj['max_pos_err_nm']:.2f} nm, {rj['max_weight_err_pct']:.3f} %")
        for kind in ("dense", "sparse"):
            ms, res, n = timed(c, kind == "sparse", a.repeats)
            ep, ew = errors(res.x, truth)
            rss = float(2 * res.cost)
            d = dict(ms=ms, runs=n, nfev=int(res.nfev), njev=int(res.njev), status=int(res.status),
                     ratio=ms / rj["rust_ms"], pos_err_nm=ep * 1e3, weight_err_pct=ew * 100, rss=rss,
                     rss_rel_diff=rss / rj["rss"] - 1.0, max_pos_diff_nm=max_pos_diff(res.x, rust_p) * 1e3)
            row["scipy_" + kind] = d
            print(f"  scipy {kind:<6} {ms:10.1f} ms (median of {n}), nfev {d['nfev']}, ratio {d['ratio']:.0f}x; "
                  f"errors vs truth {d['pos_err_nm']:.2f} nm, {d['weight_err_pct']:.3f} %; "
                  f"RSS/RSS_rust - 1 = {d['rss_rel_diff']:.1e}; max |position difference| {d['max_pos_diff_nm']:.3f} nm")
        ic = interpolant_check(c, rust_p)
        row["interpolant_check"] = ic
        print(f"  at bfpscope's parameters: RSS/RSS_rust - 1 = {ic['keys']:.1e} with Keys' cubic (numpy), "
              f"{ic['spline']:.1e} with scipy's spline (the interpolants' difference)")
        best = min(("dense", "sparse"), key=lambda k: row["scipy_" + k]["ms"])
        row["best_scipy"] = best
        row["ratio"] = row["scipy_" + best]["ratio"]
        report.append(row)
    with open(os.path.join(DIR, "compare.json"), "w") as f:
        json.dump(report, f, indent=2)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
