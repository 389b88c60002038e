#!/usr/bin/env bash
# Measures the figures quoted in the issue notes: build seconds and Mrays/s
# on 1 and 2 threads, single and packet mode, medians over repetitions.
#
#   tools/figures.sh [SCENE_DIR]     # default: $SLIMKD_SCENES or ~/.cache/slimkd-scenes
#
# Uses the embedded default scene always and stk_black_forest.obj when
# SCENE_DIR has it (fetch with ../shared/scenes/get-scenes.sh). Timings on a
# shared 2-core machine are noisy: compare ratios measured in one run.
set -euo pipefail
cd "$(dirname "$0")/.."
DIR=${1:-${SLIMKD_SCENES:-$HOME/.cache/slimkd-scenes}}
cargo build --release -q
S=target/release/slimkd
VIEWS=../shared/scenes/views.txt
[ -f "$VIEWS" ] || VIEWS=scenes/views.txt
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT

json() { python3 -c "import json,sys; j=json.load(sys.stdin); print(' '.join(str(j[k]) for k in sys.argv[1:]))" "$@"; }
median() { python3 -c "import sys,statistics; print(round(statistics.median(float(x) for x in sys.argv[1:]), 3))" "$@"; }

figures() {  # figures NAME OBJ
  local name=$1 obj=$2 kd=$TMP/$1.kd builds=()
  for _ in 1 2 3; do
    builds+=("$($S build "$obj" -o "$kd" --reorder --json | json build_s)")
  done
  echo "$name: build (level builder, all threads, std tree) median of 3: $(median "${builds[@]}") s"
  for view in 1 2 3; do
    for mode in single packet; do
      for t in 1 2; do
        r=$($S render "$kd" --views "$VIEWS" --view "$view" --mode "$mode" --threads "$t" --reps 5 --json | json mrays_per_s hits checksum)
        echo "$name view $view $mode ${t}T: Mrays/s hits checksum = $r"
      done
    done
  done
}

cp scenes/nexuiz_dieselpower.obj "$TMP/nexuiz_dieselpower.obj"
figures nexuiz_dieselpower "$TMP/nexuiz_dieselpower.obj"
if [ -f "$DIR/stk_black_forest.obj" ]; then
  figures stk_black_forest "$DIR/stk_black_forest.obj"
fi
