#!/usr/bin/env bash
# Guided sensor calibration for a field technician: camera, laser plane, conveyor scale, each checked against
# limits with a clear PASS / FAIL and what to do next. --sim runs the whole procedure on the simulated cell.
#
# usage: scripts/calibrate.sh [--sim] [--config FILE] [--calibration FILE] [--work DIR]
#   --sim               no hardware: the simulated cell renders the board pictures (non-interactive)
#   --config FILE       cellsight configuration (default: config/cellsight.yaml)
#   --calibration FILE  result file (default: calibration.yaml beside the config; with --sim: WORK/calibration.yaml,
#                       so a simulated run never touches the real cell's calibration)
#   --work DIR          folder for the pictures (default: out/calibration-YYYYMMDD-HHMMSS)
# environment: CELLSIGHT_BIN  the cellsight executable (default: build/app/cellsight, built if missing)
# exit: 0 every step PASSED, 1 a step FAILED or was refused, 2 bad arguments
set -uo pipefail
cd "$(dirname "$0")/.." || exit 2

SIM=0
CONFIG=config/cellsight.yaml
CALIBRATION=
WORK=
while [ $# -gt 0 ]; do
  case "$1" in
    --sim) SIM=1 ;;
    --config) CONFIG=${2:?--config needs a file}; shift ;;
    --calibration) CALIBRATION=${2:?--calibration needs a file}; shift ;;
    --work) WORK=${2:?--work needs a folder}; shift ;;
    -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
    *) echo "calibrate.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done

# Pass limits: tighter than the refusal limits inside cellsight, so a PASS means a good calibration, not just an
# accepted one.
LIMIT_RMS_PX=0.30          # camera reprojection error
LIMIT_COVERAGE=0.50        # share of the image the dots reached
LIMIT_LASER_MM=0.25        # stripe points from the fitted laser plane
LIMIT_ANGLE_DEG=1.0        # conveyor travel away from the cell x axis
LIMIT_LINE_MM=0.30         # board positions from a straight line of travel

BIN=${CELLSIGHT_BIN:-build/app/cellsight}
if [ ! -x "$BIN" ]; then
  echo "== building cellsight (Release) =="
  if ! { cmake -S . -B build -DCMAKE_BUILD_TYPE=Release >/dev/null &&
         cmake --build build -j"$(nproc)" --target cellsight >/dev/null; }; then
    echo "FAIL: cellsight could not be built; run scripts/setup.sh, then try again"
    exit 1
  fi
fi
[ -f "$CONFIG" ] || { echo "calibrate.sh: no configuration at $CONFIG (use --config FILE)" >&2; exit 2; }
[ -n "$WORK" ] || WORK=out/calibration-$(date +%Y%m%d-%H%M%S)
if [ -z "$CALIBRATION" ]; then
  if [ $SIM = 1 ]; then CALIBRATION=$WORK/calibration.yaml; else CALIBRATION=$(dirname "$CONFIG")/calibration.yaml; fi
fi
mkdir -p "$WORK" || { echo "calibrate.sh: cannot create $WORK" >&2; exit 2; }

FAILED=0
say() { printf '%s\n' "$*"; }
wait_for_technician() {
  [ $SIM = 1 ] && return 0
  read -r -p "   Press Enter when the pictures are in $1 (Ctrl-C to stop) " _
}
# figure NAME OUTPUT: the first number after "NAME:" in a step's output.
figure() { printf '%s\n' "$2" | awk -v key="$1:" '$1 == key { print $2; exit }'; }
# check NAME VALUE LIMIT le|ge ADVICE
check() {
  local name=$1 value=$2 limit=$3 sense=$4 advice=$5
  if [ -z "$value" ]; then say "   FAIL  $name: not reported"; FAILED=1; return; fi
  if awk -v v="$value" -v l="$limit" -v s="$sense" 'BEGIN { exit !((s == "le") ? (v <= l) : (v >= l)) }'; then
    say "   PASS  $name = $value (limit $limit)"
  else
    say "   FAIL  $name = $value (limit $limit): $advice"
    FAILED=1
  fi
}
# run_step STEP: runs cellsight calibrate STEP on WORK/STEP; prints its output; returns its exit code.
OUTPUT=
run_step() {
  local step=$1 source
  if [ $SIM = 1 ]; then source=(--sim --out "$WORK/$step"); else source=(--images "$WORK/$step"); fi
  OUTPUT=$("$BIN" --config "$CONFIG" calibrate "$step" "${source[@]}" --calibration "$CALIBRATION" 2>&1)
  local code=$?
  printf '%s\n' "$OUTPUT" | sed 's/^/   | /'
  if [ $code -ne 0 ]; then
    say "   FAIL  calibrate $step was refused (exit $code); the previous calibration stays in force."
    say "         Do what the message above says, then run this script again."
    FAILED=1
  fi
  return $code
}
template() {  # a views.yaml to fill in, for the interactive procedure
  local dir=$WORK/$1
  mkdir -p "$dir"
  [ -f "$dir/views.yaml" ] && return 0
  case $1 in
    camera) cat >"$dir/views.yaml" <<'EOF'
# Camera step: list your pictures. board: delete it for the standard cellsight board (13 x 6 dots, 40 mm rows).
format_version: 1
step: camera
views:                     # at least 6, better 10: board tilted 35-50 degrees, reaching every edge and corner
  - {file: view_00.png}
  - {file: view_01.png}
reference:
  file: reference.png      # the board in the reference fixture
  dot0_cell_m: [-0.22, 0.79, 0.12]   # dot 0 (top-left) in the cell frame, from the fixture drawing
EOF
      ;;
    laser) cat >"$dir/views.yaml" <<'EOF'
# Laser step: for each board pose one picture with the lamp on (laser off), one with the laser on (lamp off).
format_version: 1
step: laser
views:                     # at least 2, better 3: different depths and tilts
  - {board: laser_00_board.png, laser: laser_00_line.png}
  - {board: laser_01_board.png, laser: laser_01_line.png}
EOF
      ;;
    conveyor) cat >"$dir/views.yaml" <<'EOF'
# Conveyor step: the board clamped to the carrier, one picture per position with the encoder count at that moment.
format_version: 1
step: conveyor
views:                     # at least 2, better 3 about 100 mm apart
  - {file: carrier_00.png, encoder_counts: 0}
  - {file: carrier_01.png, encoder_counts: 1000}
EOF
      ;;
  esac
}

say "cellsight sensor calibration $([ $SIM = 1 ] && echo '(simulated cell)')"
say "  configuration: $CONFIG"
say "  result:        $CALIBRATION (the previous file is kept as a dated .bak copy)"
say "  pictures:      $WORK"
say ""

# --- 1. camera ------------------------------------------------------------------------------------------------
say "== 1/4 camera =="
if [ $SIM = 0 ]; then
  template camera
  say "   1. Switch the laser OFF and the calibration lamp ON. Use the calibration board (dark dots on a light plate)."
  say "   2. Hold the board in front of the camera at 1.2-1.6 m and take 10 pictures, tilting it 35-50 degrees"
  say "      left, right, up and down, and moving it so that it reaches every edge and corner of the picture."
  say "      The whole board must be in every picture, sharp and without glare. Save them as PNG in $WORK/camera."
  say "   3. Mount the board in the reference fixture on the laser plane (dot 0 top-left, face toward the camera)"
  say "      and take one more picture: reference.png. Enter dot 0's position from the fixture drawing in views.yaml."
  say "   4. List the pictures in $WORK/camera/views.yaml (a template is there)."
  wait_for_technician "$WORK/camera"
fi
if run_step camera; then
  check reprojection_rms_px "$(figure reprojection_rms_px "$OUTPUT")" $LIMIT_RMS_PX le \
    "retake blurred or badly lit pictures; make sure the board is flat"
  check reference_rms_px "$(figure reference_rms_px "$OUTPUT")" $LIMIT_RMS_PX le \
    "retake reference.png with the board seated firmly in the fixture"
  check coverage "$(figure coverage "$OUTPUT")" $LIMIT_COVERAGE ge \
    "take more pictures with the board near the edges and corners of the image"
fi
[ $FAILED = 0 ] || { say ""; say "FAIL: the camera step did not pass; fix it before the laser and conveyor steps."; exit 1; }

# --- 2. laser plane -------------------------------------------------------------------------------------------
say ""
say "== 2/4 laser plane =="
if [ $SIM = 0 ]; then
  template laser
  say "   1. Hold the board so that the laser line crosses its middle, facing between the camera and the laser."
  say "   2. For each of 3 poses (near, middle and far depth; tilted differently each time) take two pictures"
  say "      without moving the board: lamp ON / laser OFF (laser_NN_board.png), then lamp OFF / laser ON"
  say "      (laser_NN_line.png) with the exposure set so the line is bright but not saturated."
  say "   3. List the pairs in $WORK/laser/views.yaml."
  wait_for_technician "$WORK/laser"
fi
if run_step laser; then
  check laser_residual_mm "$(figure laser_residual_mm "$OUTPUT")" $LIMIT_LASER_MM le \
    "check the board is flat, the laser line is sharp and there are no reflections; retake the laser pictures"
fi

# --- 3. conveyor scale ----------------------------------------------------------------------------------------
say ""
say "== 3/4 conveyor scale =="
if [ $SIM = 0 ]; then
  template conveyor
  say "   1. Clamp the board rigidly to a carrier, face toward the camera, lamp ON, laser OFF."
  say "   2. Take a picture and note the encoder count; move the carrier about 100 mm downstream; repeat,"
  say "      three positions over about 200 mm in total. Save carrier_NN.png and the counts in views.yaml."
  wait_for_technician "$WORK/conveyor"
fi
if run_step conveyor; then
  check travel_angle_to_x_deg "$(figure travel_angle_to_x_deg "$OUTPUT")" $LIMIT_ANGLE_DEG le \
    "the conveyor does not run along the cell x axis: check the reference fixture is square to the conveyor"
  check line_residual_mm "$(figure line_residual_mm "$OUTPUT")" $LIMIT_LINE_MM le \
    "the board moved on the carrier or the counts were noted wrongly; clamp it firmly and repeat"
fi

# --- 4. support (carrier) plane --------------------------------------------------------------------------------
# Needs the three steps above: the empty carrier is scanned with the calibrated sensor.
say ""
say "== 4/4 carrier (support) plane =="
if [ $FAILED = 0 ]; then
  if [ $SIM = 1 ]; then
    support_source=(--sim)
  else
    say "   1. Hang NOTHING on the carrier; lamp off, laser on; let the empty carrier pass the sensor."
    say "   2. Scan it:  $BIN --config $CONFIG scan --out $WORK/empty_carrier.ply --calibration $CALIBRATION"
    wait_for_technician "$WORK"
    support_source=(--scan "$WORK/empty_carrier.ply")
  fi
  OUTPUT=$("$BIN" --config "$CONFIG" calibrate support "${support_source[@]}" --calibration "$CALIBRATION" 2>&1)
  code=$?
  printf '%s\n' "$OUTPUT" | sed 's/^/   | /'
  if [ $code -ne 0 ]; then
    say "   FAIL  calibrate support was refused (exit $code); the previous calibration stays in force."
    say "         Make sure the carrier was empty and flat, then run this script again."
    FAILED=1
  else
    check rms_mm "$(figure rms_mm "$OUTPUT")" 1.0 le "the carrier is not flat: straighten or replace it"
  fi
else
  say "   skipped: the steps above must pass first"
fi

say ""
if [ $FAILED = 0 ]; then
  say "PASS: camera, laser plane, conveyor and carrier plane calibrated; $CALIBRATION is in force."
  exit 0
fi
say "FAIL: repeat the failed step(s) as advised above; $CALIBRATION holds the last accepted result of each step."
exit 1
