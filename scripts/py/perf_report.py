#!/usr/bin/env python3
"""Regenerate the generated parts of docs/performance.md from one run of scripts/bench.sh.

Generated text lives between `<!-- bench:NAME -->` and `<!-- /bench:NAME -->` markers; everything
outside them (the narrative: reasoning, floors, history) is kept as written. Blocks:
  machine   the machine of the last run (CPU, cores, load average at start and end, rustc, date)
  summary   the speed table, bfpscope against its floor or its peer, ratios from the same run
  NAME      one per bench of Cargo.toml: criterion's medians, the tables the bench printed and
            its peer's results. A block whose bench did not run this time keeps its old text
            (its own date line says when it was measured); a new bench gets a new block at the
            end of the file, so adding a bench to Cargo.toml needs no change here.
A summary row whose bench did not run keeps its previous text. To add a summary row, add one
entry to ROWS.
"""
import argparse
import glob
import json
import os
import re
import statistics

SUMMARY_HEAD = "| work | bfpscope | floor or peer | ratio / gap |\n|---|---|---|---|"


def fmt_t(ns):
    if ns >= 1e9:
        return f"{ns / 1e9:.2f} s"
    if ns >= 1e6:
        return f"{ns / 1e6:.2f} ms"
    if ns >= 1e3:
        return f"{ns / 1e3:.2f} µs"
    return f"{ns:.0f} ns"


def criterion_results(crit_dir, t0, t1):
    """{full_id: (median_ns, lo_ns, hi_ns)} of the estimates written between t0 and t1.

    No slack before t0: the previous bench's last estimates are written just before the next
    bench starts, and a slack of a second listed them under the wrong bench."""
    out = {}
    for est in glob.glob(os.path.join(crit_dir, "**", "new", "estimates.json"), recursive=True):
        mt = os.path.getmtime(est)
        if not (t0 <= mt <= t1 + 1):
            continue
        try:
            bj = json.load(open(os.path.join(os.path.dirname(est), "benchmark.json")))
            e = json.load(open(est))["median"]
        except (OSError, ValueError, KeyError):
            continue
        ci = e["confidence_interval"]
        out[bj.get("full_id", est)] = (e["point_estimate"], ci["lower_bound"], ci["upper_bound"])
    return out


def load(path):
    try:
        return json.load(open(path))
    except (OSError, ValueError):
        return None


# ---- summary rows: (key, function(ctx) -> (bfpscope, floor_or_peer, ratio) or None) ----------

def crit(ctx, bench, full_id):
    return ctx["crit"].get(bench, {}).get(full_id)


def row_render(ctx):
    c = crit(ctx, "render", "render 128x128, 10 beads + 10 µm filament (ideal)")
    if c:
        return (fmt_t(c[0]) + " (criterion median)", "≈ 0.4 ms (2 cores, see Floors); target ≤ 2 ms",
                f"{c[0] / 0.4e6:.1f}× the floor" + (" ✓" if c[0] <= 2e6 else " — target not met"))


def row_plane(ctx):
    c = crit(ctx, "render", "template precompute/one plane at z = 0 (h = 20 nm, cubic)")
    if c:
        return (fmt_t(c[0]), "≈ 0.2 ms (see Floors); target ≤ 3 ms", f"{c[0] / 0.2e6:.1f}× the floor")


def row_plane_vector(ctx):
    c = crit(ctx, "vector_beam", "vector beam template/one plane at z = 0 (point dipole, default grid)")
    t = crit(ctx, "vector_beam", "vector beam template/point dipole template, construction")
    if c:
        extra = f"; the template's construction, once per optics: {fmt_t(t[0])}" if t else ""
        return (fmt_t(c[0]) + extra, "target ≤ 3 ms", ("✓" if c[0] <= 3e6 else "not met") + " (see In the vector beam)")


def row_renderer(ctx):
    c = crit(ctx, "render", "template precompute/renderer for the scene (planes for z = 0)")
    if c:
        return (fmt_t(c[0]), "target ≤ 10 ms", "✓" if c[0] <= 10e6 else "not met")


def row_fit(case, label):
    def f(ctx):
        peer = ctx["peer"].get("fit")
        if not peer:
            return None
        r = next((r for r in peer if r["case"] == case), None)
        if not r:
            return None
        d, s = r["scipy_dense"], r["scipy_sparse"]
        best = r["scipy_" + r["best_scipy"]]
        verdict = f"{best['ratio']:.0f}× faster" if best["ratio"] >= 1 else f"**scipy faster** ({1 / best['ratio']:.1f}×)"
        target = ""
        if case == "40beads_256":
            target = "; target ≥ 100×: " + ("✓" if best["ratio"] >= 100 else "not met")
        return (f"{r['rust_ms']:.1f} ms; errors {r['rust_pos_err_nm']:.2f} nm, {r['rust_weight_err_pct']:.3f} %",
                f"scipy `least_squares` trf: dense {d['ms']:.0f} ms, sparse/lsmr {s['ms']:.0f} ms; "
                f"RSS within {max(abs(d['rss_rel_diff']), abs(s['rss_rel_diff'])):.0e}, positions within "
                f"{max(d['max_pos_diff_nm'], s['max_pos_diff_nm']):.3f} nm of ours"
                + (f" (scipy's spline interpolant alone, at our parameters: {r['interpolant_check']['spline']:+.0e})"
                   if r.get("interpolant_check") else ""),
                f"{verdict} than scipy's faster set-up ({r['best_scipy']}); {d['ratio']:.0f}× vs dense{target}")
    return label, f


def row_mie(x_max):
    def f(ctx):
        peer = ctx["peer"].get("mie")
        if not peer:
            return None
        rows = [r for r in peer["sweeps"] if r["x_max"] == x_max]
        if not rows:
            return None
        ours = [r["ours_ns"] for r in rows]
        arr = [r["jit_array_ns"] / r["ours_ns"] for r in rows]
        one = [r["jit_one_ns"] / r["ours_ns"] for r in rows]
        slower = min(arr) < 1
        verdict = (f"array: {min(arr):.2f}–{max(arr):.2f}× " + ("(**miepython faster** where < 1)" if slower else "faster")
                   + f"; one at a time: {min(one):.1f}–{max(one):.1f}×")
        return (f"{min(ours) / 1e3:.2f}–{max(ours) / 1e3:.2f} µs per sphere",
                f"miepython {peer['version']} with numba (MIEPYTHON_USE_JIT=1, warmed), same 1000 spheres",
                verdict)
    return f"Mie efficiencies, array sweep x ≤ {x_max:g}, 3 indices", f


def row_binding(ctx):
    err = ctx["stderr"].get("engine", "")
    m = re.search(r"binding_call: ([\d.]+) M calls/s.*empty loop: ([\d.]+) M", err)
    if m:
        return (f"{m.group(1)} M calls/s", f"empty Rhai loop: {m.group(2)} M iterations/s", "—")


def row_instrument(ctx):
    # the instrument_time bench's table: | link | dwell | drivers | ms per point | settle + dwell |
    # ratio | ...; the summary shows the drivers' current protocol ("after")
    rows = []
    for line in ctx["log"].get("instrument_time", "").splitlines():
        c = [x.strip() for x in line.strip().strip("|").split("|")]
        if len(c) >= 6 and c[2] == "after" and c[5].endswith("×"):
            rows.append(c)
    if rows:
        us = "; ".join(f"{c[0]}, dwell {c[1]}: {c[3]} ms" for c in rows)
        ratio = "; ".join(f"{c[5]}" for c in rows)
        met = all(float(c[5].rstrip("×")) <= 1.1 for c in rows)
        return (us, "settle + dwell (target: within 10 %)",
                ratio + (" ✓" if met else " — not met: the emulated stage's 2 ms move and, at 115200 baud, the wire (see Instrument time)"))


def row_raster(ctx):
    # the raster_time bench's table: | link | raster wall | line | target | ratio | points | ... |
    rows = {}
    for line in ctx["log"].get("raster_time", "").splitlines():
        c = [x.strip() for x in line.strip().strip("|").split("|")]
        if len(c) == 7 and c[4].endswith("×") and c[0] in ("pty full speed", "TCP, 1 ms latency"):
            rows[c[0]] = c
    if rows:
        us = "; ".join(f"{k}: {v[1]}" for k, v in rows.items())
        pts = rows.get("pty full speed", [""] * 7)[5]
        ratio = "; ".join(f"{k}: {v[4]} the target" for k, v in rows.items())
        return (us, f"target 1.2 × (4096 ms + turnarounds) = {next(iter(rows.values()))[3]}; point by point {pts}", ratio)


ROWS = [
    ("scan per point on the emulators", row_instrument),
    ("64 × 64 raster at 1 ms per pixel on the emulators (PI wave generator + Red Pitaya)", row_raster),
    ("render 128 × 128, 10 beads + 10 µm filament (default vector beam)", row_render),
    ("one template plane, paraxial beam (scalar cone rule)", row_plane),
    ("one template plane, vector beam (the default; point dipole)", row_plane_vector),
    ("renderer for a scene (domain check remembered)", row_renderer),
    row_fit("3beads_64", "fit, 3 beads, 64 × 64"),
    row_fit("11beads_128", "fit, 11 beads, 128 × 128"),
    row_fit("40beads_256", "fit, 40 beads, 256 × 256"),
    (*row_mie(10.0),),
    (*row_mie(1000.0),),
    ("binding call from Rhai", row_binding),
]


def blocks(text):
    return {m.group(1): m.group(2) for m in re.finditer(r"<!-- bench:(\S+) -->\n(.*?)<!-- /bench:\1 -->", text, re.S)}


def set_block(text, name, body, where_missing):
    body = body.rstrip("\n") + "\n"
    pat = re.compile(r"(<!-- bench:%s -->\n)(.*?)(<!-- /bench:%s -->)" % (re.escape(name), re.escape(name)), re.S)
    if pat.search(text):
        return pat.sub(lambda m: m.group(1) + body + m.group(3), text)
    block = f"<!-- bench:{name} -->\n{body}<!-- /bench:{name} -->\n"
    return where_missing(text, block)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out-dir", required=True)
    ap.add_argument("--criterion", required=True)
    ap.add_argument("--doc", required=True)
    a = ap.parse_args()
    start = load(os.path.join(a.out_dir, "machine.start.json"))
    end = load(os.path.join(a.out_dir, "machine.end.json"))
    ran = {}
    for line in open(os.path.join(a.out_dir, "ran.txt")):
        n, t0, t1, status, peer = line.rstrip("\n").split("\t")
        ran[n] = dict(t0=float(t0), t1=float(t1), status=status, peer=peer)
    ctx = dict(ran=ran, crit={}, peer={}, stderr={}, log={})
    for n, r in ran.items():
        ctx["crit"][n] = criterion_results(a.criterion, r["t0"], r["t1"])
        ctx["stderr"][n] = open(os.path.join(a.out_dir, f"{n}.err"), errors="replace").read()
        logf = os.path.join(a.out_dir, f"{n}.log")
        ctx["log"][n] = open(logf, errors="replace").read() if os.path.exists(logf) else ""
        p = load(os.path.join(a.out_dir, f"{n}.peer.json"))
        if p is not None:
            ctx["peer"][n] = p
    text = open(a.doc).read()
    old = blocks(text)

    def after_intro(t, block):
        i = t.find("\n## ")
        return t[:i + 1] + block + "\n" + t[i + 1:] if i >= 0 else t + "\n" + block

    def at_end(t, block):
        if "\n## Benchmark results (generated)\n" not in t:
            t = t.rstrip("\n") + "\n\n## Benchmark results (generated)\n\nOne block per bench of Cargo.toml, written by `scripts/bench.sh`.\n"
        return t.rstrip("\n") + "\n\n" + block

    mach = (f"Last run of `scripts/bench.sh {' '.join(ran)}`: {start['when']}; {start['cpu']}, {start['cores']} cores; "
            f"load average (1, 5, 15 min) {' '.join(start['load'])} at the start, {' '.join(end['load'])} at the end; "
            f"{start['rustc']}. The machine is shared: read ratios measured in the same run, not absolute times.\n")
    # Summary: rows computed now, else the previous text of the row.
    prev_rows = {}
    for line in old.get("summary", "").splitlines():
        if line.startswith("| ") and not line.startswith("| work"):
            prev_rows[line.split("|")[1].strip()] = line
    lines = [SUMMARY_HEAD]
    for key, f in ROWS:
        v = None
        try:
            v = f(ctx)
        except (KeyError, TypeError, ValueError, ZeroDivisionError):
            v = None
        if v:
            lines.append(f"| {key} | {v[0]} | {v[1]} | {v[2]} |")
        elif key in prev_rows:
            lines.append(prev_rows[key])
        else:
            lines.append(f"| {key} | not measured yet | | |")
    summary = ("Ratios: peer time / bfpscope time (or bfpscope time / floor); rows not measured in the last run "
               "keep the numbers of the run that measured them (see that bench's block for its date).\n\n"
               + "\n".join(lines) + "\n")
    text = set_block(text, "machine", mach, after_intro)
    text = set_block(text, "summary", summary, lambda t, b: t.replace("<!-- /bench:machine -->\n", "<!-- /bench:machine -->\n\n" + b, 1))
    for n, r in ran.items():
        body = [f"`cargo bench --features bench --bench {n}` — {start['when']}, load {' '.join(start['load'])} → {' '.join(end['load'])}; "
                f"bench: {r['status']}; peer: {r['peer']}.", ""]
        c = ctx["crit"][n]
        if c:
            body += ["| criterion benchmark | median | 95 % interval |", "|---|---|---|"]
            body += [f"| {k} | {fmt_t(v[0])} | {fmt_t(v[1])} – {fmt_t(v[2])} |" for k, v in sorted(c.items())]
            body.append("")
        log = open(os.path.join(a.out_dir, f"{n}.log"), errors="replace").read()
        printed = [l for l in log.splitlines() if l.startswith("|") or re.match(r"^\S+: [\d.]+ ms \(median", l)]
        if printed:
            body += ["What the bench printed:", ""] + [l if l.startswith("|") else f"- {l}" for l in printed] + [""]
        peer_log = os.path.join(a.out_dir, f"{n}.peer.log")
        if os.path.exists(peer_log):
            pl = open(peer_log, errors="replace").read().splitlines()
            keep = [l for l in pl if not l.startswith(("   Compiling", "    Finished", "     Running", "warning", "==")) and l.strip()]
            body += ["Peer output:", "", "```"] + keep[-60:] + ["```", ""]
        text = set_block(text, n, "\n".join(body), at_end)
    open(a.doc, "w").write(text)


if __name__ == "__main__":
    main()
