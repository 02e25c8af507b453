#!/usr/bin/env python3
"""Compare bfpscope's Mie tier with miepython (speed and agreement) and print
high-precision reference values.

Usage (from the repository root):

    python3 scripts/py/mie_compare.py compare      # needs miepython (+ numpy)
    python3 scripts/py/mie_compare.py reference X M_RE M_IM [EXTRA]   # needs mpmath

`compare` builds and runs `MIE_COMPARE_JSON=1 cargo bench --features bench --bench mie` (the Rust timings and
values on the grid x = 0.1 ... 1000, and its time per sphere on array sweeps of 1000 spheres
over x ≤ 10 and x ≤ 1000), then, in the same run, times miepython's
`efficiencies_mx` on the same grid, once with its default pure-Python/numpy backend and once
with its numba JIT backend (MIEPYTHON_USE_JIT=1, compile time excluded), and prints per-point
speed ratios and relative agreement. The sweeps are timed both ways: the whole array in one
`efficiencies_mx` call (numba's fast path, warmed up) and one sphere per call; with
MIE_COMPARE_OUT=FILE the numbers are also written as JSON (scripts/bench.sh uses it). The machine is shared and noisy: read the ratios, not the
absolute times. Nothing in the test suite needs this script or miepython.

Index convention: bfpscope takes m = n + i k (Bohren-Huffman, k >= 0 absorbs); miepython takes
n - i k. The script converts.

`reference` evaluates BH eq. 4.88 with 60+ significant digits (mpmath): D_n(mx) by the
BHMIE-style downward recurrence from a zero start far above max(N, |mx|) (independent of the
Lentz start used in the Rust code), psi_n and chi_n by upward recurrence with enough extra
digits to absorb the growth. It sums N = int(x + 4.05 x^(1/3) + 2) + EXTRA terms (default 40)
and prints Q_ext, Q_sca, Q_back, g to 20 digits. These are the "mpmath" values in tests/mie.rs.
"""

import json
import math
import os
import subprocess
import sys
import time


def reference(x, m, extra=40):
    import mpmath as mp

    n_terms = int(x + 4.05 * x ** (1.0 / 3.0) + 2) + extra
    # digits lost in the upward psi recurrence grow like log10 of chi_N * psi_0 / psi_N
    mp.mp.dps = 60 + int(n_terms * max(1.0, math.log10(2.0 * n_terms / x) + 1.0))
    x = mp.mpf(x)
    m = mp.mpc(m)
    z = m * x
    n_start = int(n_terms + abs(complex(z)) + 60)
    d = [mp.mpc(0)] * (n_start + 2)
    for n in range(n_start, 0, -1):
        d[n - 1] = n / z - 1 / (d[n] + n / z)
    psi_prev2, psi_prev = mp.cos(x), mp.sin(x)
    chi_prev2, chi_prev = -mp.sin(x), mp.cos(x)
    a, b = [], []
    for n in range(1, n_terms + 1):
        psi_n = (2 * n - 1) / x * psi_prev - psi_prev2
        chi_n = (2 * n - 1) / x * chi_prev - chi_prev2
        xi_n = psi_n - 1j * chi_n
        xi_nm1 = psi_prev - 1j * chi_prev
        da = d[n] / m + n / x
        db = m * d[n] + n / x
        a.append((da * psi_n - psi_prev) / (da * xi_n - xi_nm1))
        b.append((db * psi_n - psi_prev) / (db * xi_n - xi_nm1))
        psi_prev2, psi_prev = psi_prev, psi_n
        chi_prev2, chi_prev = chi_prev, chi_n
    rng = range(1, n_terms + 1)
    qext = 2 / x**2 * sum((2 * n + 1) * (a[n - 1] + b[n - 1]).real for n in rng)
    qsca = 2 / x**2 * sum((2 * n + 1) * (abs(a[n - 1]) ** 2 + abs(b[n - 1]) ** 2) for n in rng)
    back = sum((2 * n + 1) * (-1) ** n * (a[n - 1] - b[n - 1]) for n in rng)
    qback = abs(back) ** 2 / x**2
    gs = 0
    for n in rng:
        if n < n_terms:
            gs += mp.mpf(n * (n + 2)) / (n + 1) * (a[n - 1] * mp.conj(a[n]) + b[n - 1] * mp.conj(b[n])).real
        gs += mp.mpf(2 * n + 1) / (n * (n + 1)) * (a[n - 1] * mp.conj(b[n - 1])).real
    g = 4 / x**2 * gs / qsca
    return [mp.nstr(v, 20) for v in (qext, qsca, qback, g)]


def rust_dump(repo):
    env = dict(os.environ, MIE_COMPARE_JSON="1")
    out = subprocess.run(
        ["cargo", "bench", "--bench", "mie"], cwd=repo, env=env, capture_output=True, text=True, check=True
    ).stdout
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def time_miepython(points, jit):
    """Run in a subprocess so that MIEPYTHON_USE_JIT takes effect before import."""
    env = dict(os.environ, MIEPYTHON_USE_JIT="1" if jit else "0")
    code = r"""
import json, sys, time
import miepython as mie
pts = json.loads(sys.stdin.read())
out = []
for p in pts:
    m = complex(p["m_re"], -p["m_im"])   # miepython: n - i k
    x = p["x"]
    r = mie.efficiencies_mx(m, x)        # warm-up (and JIT compile)
    ts = []
    for _ in range(5):
        n = 0
        t0 = time.perf_counter()
        while True:
            r = mie.efficiencies_mx(m, x)
            n += 1
            if time.perf_counter() - t0 > 0.06:
                break
        ts.append((time.perf_counter() - t0) / n * 1e9)
    ts.sort()
    out.append({"x": x, "m_re": p["m_re"], "m_im": p["m_im"], "qext": float(r[0]), "qsca": float(r[1]),
                "qback": float(r[2]), "g": float(r[3]), "ns_per_call": ts[len(ts)//2],
                "version": mie.__version__})
print(json.dumps(out))
"""
    res = subprocess.run(
        [sys.executable, "-c", code], input=json.dumps(points), env=env, capture_output=True, text=True, check=True
    )
    return json.loads(res.stdout)


def time_miepython_sweeps(sweeps, jit):
    """Time miepython on the Rust bench's array sweeps, in a subprocess (MIEPYTHON_USE_JIT must
    be set before import): the whole array in one `efficiencies_mx` call (warmed up: the first
    call compiles), and the same spheres one call at a time. ns per sphere, median of 5 rounds."""
    env = dict(os.environ, MIEPYTHON_USE_JIT="1" if jit else "0")
    code = r"""
import json, sys, time
import numpy as np
import miepython as mie
out = []
for s in json.loads(sys.stdin.read()):
    n, x_max = s["n"], s["x_max"]
    xs = 0.1 + (x_max - 0.1) * np.arange(1, n + 1) / n
    m = complex(s["m_re"], -s["m_im"])
    mie.efficiencies_mx(m, xs)          # warm-up (and JIT compile)
    mie.efficiencies_mx(m, float(xs[0]))
    def rounds(f, budget):
        ts = []
        for _ in range(5):
            k = 0
            t0 = time.perf_counter()
            while True:
                f()
                k += 1
                if time.perf_counter() - t0 > budget:
                    break
            ts.append((time.perf_counter() - t0) / k / n * 1e9)
        ts.sort()
        return ts[len(ts) // 2]
    arr = rounds(lambda: mie.efficiencies_mx(m, xs), 0.1)
    one = rounds(lambda: [mie.efficiencies_mx(m, float(x)) for x in xs], 0.0)
    out.append(dict(s, array_ns=arr, one_ns=one))
print(json.dumps(out))
"""
    res = subprocess.run(
        [sys.executable, "-c", code], input=json.dumps(sweeps), env=env, capture_output=True, text=True, check=True
    )
    return json.loads(res.stdout)


def rel(a, b):
    return abs(a - b) / abs(b) if b != 0 else abs(a)


def compare(repo):
    try:
        import miepython  # noqa: F401
    except ImportError:
        print("miepython is not importable (pip install miepython numpy); nothing to compare.")
        return 1
    rust1 = rust_dump(repo)
    points = [p for p in rust1 if p["tag"] == "default"]
    sweeps = [p for p in rust1 if p["tag"] == "sweep"]
    sw_nojit = time_miepython_sweeps(sweeps, jit=False)
    sw_jit = time_miepython_sweeps(sweeps, jit=True)
    py_nojit = time_miepython(points, jit=False)
    py_jit = time_miepython(points, jit=True)
    rust2 = rust_dump(repo)  # second Rust run: the machine is noisy, take the faster of the two
    print(f"miepython {py_nojit[0]['version']}; ratios = miepython time / bfpscope time (same run)")
    hdr = "| x | m | N ours | ours ns | nojit/ours | jit/ours | max rel diff Qext,Qsca,g (ours default) | rel diff Qback | max rel diff, same N as miepython |"
    print(hdr)
    print("|" + "---|" * 9)
    ratios_nojit, ratios_jit, worst = [], [], 0.0
    for p, q_nj, q_j in zip(points, py_nojit, py_jit):
        key = (p["x"], p["m_re"], p["m_im"])
        r2 = next(r for r in rust2 if r["tag"] == "default" and (r["x"], r["m_re"], r["m_im"]) == key)
        same = next(r for r in rust1 if r["tag"] == "miepython_terms" and (r["x"], r["m_re"], r["m_im"]) == key)
        ns = min(p["ns_per_call"], r2["ns_per_call"])
        d = max(rel(p[k], q_nj[k]) for k in ("qext", "qsca"))
        d = max(d, abs(p["g"] - q_nj["g"]) / max(abs(q_nj["g"]), 1e-300))
        db = rel(p["qback"], q_nj["qback"])
        ds = max(rel(same[k], q_nj[k]) for k in ("qext", "qsca", "qback", "g"))
        worst = max(worst, d)
        ratios_nojit.append(q_nj["ns_per_call"] / ns)
        ratios_jit.append(q_j["ns_per_call"] / ns)
        m = f"{p['m_re']}+{p['m_im']}i"
        print(f"| {p['x']:g} | {m} | {p['n_terms']} | {ns:.0f} | {ratios_nojit[-1]:.1f} | {ratios_jit[-1]:.1f} | {d:.1e} | {db:.1e} | {ds:.1e} |")
    gm = lambda v: math.exp(sum(math.log(t) for t in v) / len(v))
    print(f"\nspeed ratio vs miepython (pure Python backend, its default): min {min(ratios_nojit):.1f}x, "
          f"geometric mean {gm(ratios_nojit):.1f}x")
    print(f"speed ratio vs miepython (numba JIT backend): min {min(ratios_jit):.1f}x, geometric mean {gm(ratios_jit):.1f}x")
    print(f"worst relative difference in Qext/Qsca/g (ours default terms vs miepython): {worst:.1e}")
    print("\nArray sweeps: 1000 spheres, x evenly spaced over (0.1, x_max]; ns per sphere; "
          "ratio = miepython / bfpscope (< 1: miepython is faster)")
    print("| x ≤ | m | bfpscope | jit, array | ratio | jit, one at a time | ratio | no jit, array | ratio | no jit, one at a time | ratio |")
    print("|" + "---|" * 11)
    sweep_rows = []
    for s, nj, j in zip(sweeps, sw_nojit, sw_jit):
        key = (s["x_max"], s["m_re"], s["m_im"])
        s2 = next(r for r in rust2 if r["tag"] == "sweep" and (r["x_max"], r["m_re"], r["m_im"]) == key)
        ours = min(s["ns_per_sphere"], s2["ns_per_sphere"])
        row = dict(x_max=s["x_max"], m=f"{s['m_re']}+{s['m_im']}i", ours_ns=ours, jit_array_ns=j["array_ns"],
                   jit_one_ns=j["one_ns"], nojit_array_ns=nj["array_ns"], nojit_one_ns=nj["one_ns"])
        sweep_rows.append(row)
        print(f"| {s['x_max']:g} | {row['m']} | {ours:.0f} | {j['array_ns']:.0f} | {j['array_ns'] / ours:.2f} | "
              f"{j['one_ns']:.0f} | {j['one_ns'] / ours:.1f} | {nj['array_ns']:.0f} | {nj['array_ns'] / ours:.1f} | "
              f"{nj['one_ns']:.0f} | {nj['one_ns'] / ours:.1f} |")
    if os.environ.get("MIE_COMPARE_OUT"):
        with open(os.environ["MIE_COMPARE_OUT"], "w") as f:
            json.dump(dict(version=py_nojit[0]["version"], sweeps=sweep_rows,
                           points=[dict(x=p["x"], m=f"{p['m_re']}+{p['m_im']}i", ours_ns=min(p["ns_per_call"], next(
                               r for r in rust2 if r["tag"] == "default" and (r["x"], r["m_re"], r["m_im"]) == (p["x"], p["m_re"], p["m_im"]))["ns_per_call"]),
                                        nojit_ns=a["ns_per_call"], jit_ns=b["ns_per_call"]) for p, a, b in zip(points, py_nojit, py_jit)]),
                      f, indent=2)
    return 0


def main(argv):
    repo = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
    if len(argv) >= 2 and argv[1] == "reference":
        x = float(argv[2])
        m = complex(float(argv[3]), float(argv[4]))
        extra = int(argv[5]) if len(argv) > 5 else 40
        print(" ".join(reference(x, m, extra)))
        return 0
    if len(argv) >= 2 and argv[1] == "compare":
        return compare(repo)
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv))
