#!/usr/bin/env bash
# bench_scale (issue 11): the cell with N part types of the random catalogue generator, end to end through the
# executable as a user drives it (scripts/eval_catalogue.sh: catalogue, calibration, teach SCANS simulated passes of
# every taught part, train, eval of EVAL_COUNT held-out passes of every part, untaught ones included), then `run`
# on the simulated cell. One table row per N:
#   database on disk (all, templates, taught scans), teach time per part, training time, decision median / max
#   (eval's per-scan time: features + SVM + cascade), accuracy and wrong ids on held-out passes of taught parts,
#   untaught passes that came out unknown, and the peak RSS of `run --sim --parts RUN_PARTS` with that database.
# Figures only, not a pass/fail test, and long: ~0.7 s per taught pass on this 2-core machine (300 parts x 12 passes
# is about 45 min of teaching alone), so it is not part of CI. README "Benchmarks" holds the table.
#
# usage: tests/bench/bench_scale.sh [N ...]            (default: 15 50)
# environment: CELLSIGHT_BIN (build/app/cellsight), WORK (out/bench_scale; each N in WORK/nN, which must not exist),
#              SEED (catalogue seed, 9501), SCANS (12), EVAL_COUNT (3), RUN_PARTS (20)
set -euo pipefail
cd "$(dirname "$0")/../.."

BIN=${CELLSIGHT_BIN:-build/app/cellsight}
[ -x "$BIN" ] || { echo "bench_scale.sh: no executable at $BIN" >&2; exit 2; }
BIN=$(realpath "$BIN")
WORK=${WORK:-out/bench_scale}
SEED=${SEED:-9501}
SCANS=${SCANS:-12}
EVAL_COUNT=${EVAL_COUNT:-3}
RUN_PARTS=${RUN_PARTS:-20}
[ $# -gt 0 ] || set -- 15 50
mkdir -p "$WORK"
TABLE=$WORK/table.md

mb() { awk -v b="$1" 'BEGIN { printf "%.1f", b / 1e6 }'; }
at_step() { grep -F "$2" "$1" | sed -n 's/.*\[at \([0-9]*\) s\].*/\1/p' | head -1; }

if [ ! -f "$TABLE" ]; then
  {
    echo "| parts | taught | database | templates | scans | teach s/part | train s | decision median / max ms | accuracy | wrong ids | untaught -> unknown | run RSS |"
    echo "|---|---|---|---|---|---|---|---|---|---|---|---|"
  } >"$TABLE"
fi
for N in "$@"; do
  DIR=$WORK/n$N
  echo "== bench_scale: $N parts in $DIR"
  CELLSIGHT_BIN=$BIN WORK=$DIR scripts/eval_catalogue.sh "$SEED" "$N" "$SCANS" "$EVAL_COUNT" >"$DIR.log" 2>&1 ||
    { echo "bench_scale.sh: eval_catalogue failed, see $DIR.log" >&2; exit 1; }
  parts_taught=$("$BIN" --config "$DIR/cellsight.yaml" --models "$DIR/models" parts list 2>/dev/null |
    awk 'NR > 1 && $1 ~ /^rnd/' | wc -l)
  t_teach=$(at_step "$DIR.log" "3. teaching")
  t_train=$(at_step "$DIR.log" "   training")
  t_eval=$(at_step "$DIR.log" "4. eval")
  teach_per_part=$(awk -v a="$t_teach" -v b="$t_train" -v n="$parts_taught" 'BEGIN { printf "%.1f", (b - a) / n }')
  train_s=$((t_eval - t_train))
  db=$(du -sb "$DIR/models" | cut -f1)
  templates=$(du -sb "$DIR/models/templates" | cut -f1)
  scans=$(du -sb "$DIR/models/scans" | cut -f1)
  accuracy=$(sed -n 's/^  accuracy *\([0-9.]*\) %.*/\1 %/p' "$DIR/eval.txt")
  wrong=$(sed -n 's/^  wrong ids *\([0-9]*\).*/\1/p' "$DIR/eval.txt")
  untaught=$(sed -n 's/^  not taught *\([0-9]* of [0-9]*\).*/\1/p' "$DIR/eval.txt")
  decision=$(sed -n 's/^  time .*max \([0-9.]*\) ms .*median \([0-9.]*\)).*/\2 \/ \1/p' "$DIR/eval.txt")
  # Peak RSS of the production loop with this database on the simulated cell.
  rss_kb=$(/usr/bin/time -f "%M" "$BIN" --config "$DIR/cellsight.yaml" --models "$DIR/models" --log-level warn \
    run --sim --parts "$RUN_PARTS" --port 0 --calibration "$DIR/calibration/calibration.yaml" 2>&1 >/dev/null | tail -1)
  row="| $N | $parts_taught | $(mb "$db") MB | $(mb "$templates") MB | $(mb "$scans") MB | $teach_per_part | $train_s | $decision | $accuracy | $wrong | $untaught | $(awk -v k="$rss_kb" 'BEGIN { printf "%.0f MB", k / 1e3 }') |"
  echo "$row" | tee -a "$TABLE"
done
echo "table: $TABLE"
