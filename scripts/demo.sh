#!/usr/bin/env bash
# The demo, on data it makes itself: a synthetic study of six `cup` training sessions and one test
# session each on `cup`, `kidney`, `liver` and `glove`; the distance of one session against its
# true gap; the leave-one-session-out HMM ensemble; the held-out table; and demo/demo.rrd, the
# Rerun recording of the kidney test session. Sets up .venv on first use. Outputs go to demo/.
# DEMO_SIZE (default 480x270) and DEMO_FRAMES (default 150) make it bigger or smaller; DEMO_OUT (default
# demo) is where it writes. Results go to stdout, the commands it runs and progress bars to stderr.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
OUT="${DEMO_OUT:-demo}"
SIZE="${DEMO_SIZE:-480x270}"
FRAMES="${DEMO_FRAMES:-150}"
run() { echo "+ $*" >&2; "$@"; }

make_session() {  # name phantom seed; a session is complete once its session.json exists
  if [ ! -f "$OUT/sessions/$1/session.json" ]; then
    run contact-viz synth "$OUT/sessions/$1" --phantom "$2" --seed "$3" --frames "$FRAMES" --size "$SIZE" --overwrite
  fi
}
for k in 0 1 2 3 4 5; do make_session "cup_train_$k" cup "$k"; done
make_session cup_test cup 100
make_session kidney_test kidney 101
make_session liver_test liver 102
make_session glove_test glove 103

echo; echo "== 1. The minimum-distance patch on every frame, against the generator's true gap"
run contact-viz extract "$OUT/sessions/cup_test" -o "$OUT/results/cup_test/features.csv"
run python recipes/check_against_truth.py "$OUT/sessions/cup_test" "$OUT/results/cup_test/features.csv"

echo; echo "== 2. The leave-one-session-out HMM ensemble on the six cup sessions"
run contact-viz fit "$OUT"/sessions/cup_train_? -o "$OUT/model.json" --cache-dir "$OUT/cache"

echo; echo "== 3. Held-out evaluation (Table 1 of the paper, on synthetic data)"
run contact-viz evaluate "$OUT/model.json" "$OUT"/sessions/{cup,kidney,liver,glove}_test \
  --per-frame "$OUT/results/per_frame.csv" --json "$OUT/results/metrics.json" --markdown --cache-dir "$OUT/cache"

echo; echo "== 4. Diagnostics: mask, depth and force failures in the test sessions (none in clean synthetic data)"
run contact-viz check "$OUT"/sessions/{cup,kidney,liver,glove}_test --json "$OUT/results/checks.json"

echo; echo "== 5. The Rerun recording of the kidney test session"
run contact-viz "$OUT/sessions/kidney_test" --model "$OUT/model.json" --save "$OUT/demo.rrd"
echo
echo "Open the recording with:  .venv/bin/rerun $OUT/demo.rrd"
