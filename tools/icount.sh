#!/usr/bin/env bash
# Deterministic cost of a tree build: instructions, conditional branches and
# mispredicted branches (callgrind's predictor model) spent inside
# `slimkd::build::level::build` on 1 thread; loading and writing are not
# counted. Wall times on the shared 2-core machine move by 15-25% between
# runs of the same binary; these counts repeat exactly, so they back a
# speed claim: compare two binaries on one scene.
#
#   tools/icount.sh SCENE [BIN...] [-- BUILD_ARGS...]
#
# BIN defaults to target/release/slimkd (built first). BUILD_ARGS go to
# `slimkd build` (e.g. `-- --tiny 0`). SCENE may be a `.kds` cache
# (`slimkd convert`), which loads in a fraction of the OBJ's time.
# Needs valgrind (Debian: `apt-get install valgrind`). Valgrind has no
# AVX-512, so kernels with runtime dispatch run their AVX2 version here.
# A 270 K-triangle scene takes about two minutes per binary.
set -euo pipefail
usage() { sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//'; }
if [ $# -lt 1 ]; then
  usage >&2
  exit 2
fi
if [ "$1" = -h ] || [ "$1" = --help ]; then
  usage
  exit 0
fi
command -v valgrind >/dev/null || { echo "icount: valgrind is not installed" >&2; exit 1; }
scene=$1
shift
bins=()
while [ $# -gt 0 ] && [ "$1" != -- ]; do
  bins+=("$1")
  shift
done
[ $# -gt 0 ] && shift
if [ ${#bins[@]} -eq 0 ]; then
  (cd "$(dirname "$0")/.." && cargo build --release -q)
  bins=("$(dirname "$0")/../target/release/slimkd")
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for bin in "${bins[@]}"; do
  valgrind --tool=callgrind --branch-sim=yes --callgrind-out-file="$tmp/cg.out" \
    '--toggle-collect=slimkd::build::level::build' \
    "$bin" build "$scene" -o "$tmp/out.kd" --threads 1 "$@" >/dev/null 2>"$tmp/log" ||
    { cat "$tmp/log" >&2; exit 1; }
  python3 - "$bin" "$tmp/log" <<'EOF'
import re, sys
bin_, log = sys.argv[1], open(sys.argv[2]).read()
def count(label):
    m = re.search(label + r":\s+([\d,]+)", log)
    return int(m.group(1).replace(",", "")) if m else 0
ir, br, mis = count("I\s+refs"), count("Branches"), count("Mispredicts")
print(f"{bin_}: {ir / 1e9:.3f} G instructions, {br / 1e9:.3f} G branches, "
      f"{mis / 1e6:.1f} M mispredicted")
EOF
done
