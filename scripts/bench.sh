#!/usr/bin/env bash
# Run the benchmarks and their peers in one run and regenerate docs/performance.md.
#
#   scripts/bench.sh              every [[bench]] of Cargo.toml, then every peer
#   scripts/bench.sh fit mie      a subset (names as in Cargo.toml); other sections of
#                                 docs/performance.md keep their previous numbers
#
# Each bench runs as `cargo bench --features bench --bench NAME`; criterion's estimates are read from
# $CARGO_TARGET_DIR/criterion/**/new/estimates.json (those written during that bench's run) and
# anything the bench prints as a Markdown table is kept. A bench with a peer (a Python script
# timing the tool a user would pick instead, in the same run) lists it in PEERS below: one line.
# Needs numpy/scipy (fit) and miepython + numba (mie) for the peers; a peer that cannot run is
# reported as such in the table. The test suite does not need any of this.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
cd "$ROOT"
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
OUT="$TARGET/bench_report"
mkdir -p "$OUT"

# bench name -> peer command (run after the bench; writes $OUT/NAME.peer.json).
declare -A PEERS=(
  [fit]="python3 scripts/py/fit_compare.py --json $OUT/fit.peer.json"
  [mie]="env MIE_COMPARE_OUT=$OUT/mie.peer.json python3 scripts/py/mie_compare.py compare"
)

ALL=$(awk '/^\[\[bench\]\]/{b=1;next} b&&/^name *=/{gsub(/[" ]/,"",$0);sub(/name=/,"",$0);print;b=0}' Cargo.toml)
if [ $# -gt 0 ]; then
  for n in "$@"; do
    grep -qx "$n" <<<"$ALL" || { echo "bench.sh: unknown bench '$n' (Cargo.toml lists: $(echo $ALL))" >&2; exit 2; }
  done
  RUN="$*"
else
  RUN=$(echo $ALL)
fi

machine() {
  python3 - "$1" <<'PY'
import json, os, subprocess, sys, time
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "unknown")
print(json.dumps(dict(when=time.strftime("%Y-%m-%d %H:%M:%S %Z"), epoch=time.time(), cpu=cpu,
                      cores=os.cpu_count(), load=open("/proc/loadavg").read().split()[:3],
                      rustc=subprocess.run(["rustc", "-V"], capture_output=True, text=True).stdout.strip())))
PY
}

machine start > "$OUT/machine.start.json"
: > "$OUT/ran.txt"
for n in $RUN; do
  echo "== cargo bench --features bench --bench $n" >&2
  t0=$(date +%s.%N)
  status=ok
  cargo bench --features bench --bench "$n" > "$OUT/$n.log" 2> "$OUT/$n.err" || status="failed (exit $?, see $OUT/$n.err)"
  t1=$(date +%s.%N)
  peer=none
  rm -f "$OUT/$n.peer.json" "$OUT/$n.peer.log"
  if [ -n "${PEERS[$n]:-}" ]; then
    echo "== peer: ${PEERS[$n]}" >&2
    if bash -c "${PEERS[$n]}" > "$OUT/$n.peer.log" 2>&1; then peer=ok; else peer="failed (see $OUT/$n.peer.log)"; fi
  fi
  printf '%s\t%s\t%s\t%s\t%s\n' "$n" "$t0" "$t1" "$status" "$peer" >> "$OUT/ran.txt"
done
machine end > "$OUT/machine.end.json"
python3 scripts/py/perf_report.py --out-dir "$OUT" --criterion "$TARGET/criterion" --doc docs/performance.md
echo "docs/performance.md regenerated (raw logs in $OUT)" >&2
