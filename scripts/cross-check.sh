#!/usr/bin/env bash
# The proof that the cross-built cellsight works (issue 16): the target's binary (scripts/cross-build.sh TARGET)
# runs under qemu-user with the sysroot as its library root and must answer as the native binary does:
#   1. `help` and `sim --list` print the same text;
#   2. with the native binary: calibrate the simulated sensor, teach PARTS (COUNT passes each) and train, scan
#      three parts (seeds not used for teaching);
#   3. `classify --json` of the three scans by the native binary, and by the target's binary under qemu with a copy
#      of the model database (same configuration and calibration): the same decision (status, part, id) and pose
#      within 1 um (x, y, z) and 0.001 deg (theta, rx, ry).
# The site configuration gives the cascade its largest verification budget (3000 ms) and the decision a 60 s
# deadline, so that the emulated binary, several times slower, verifies the same candidates as the native one
# instead of running out of time.
# Exit 0 when everything matches, 1 on a mismatch or failure, 2 on bad arguments.
#
# usage: scripts/cross-check.sh TARGET        (TARGET: aarch64)
# environment: CELLSIGHT_BIN  the native executable (default: build/app/cellsight, built in Release if missing)
#              WORK           the work folder (default: out/cross-check-TARGET; emptied first)
set -euo pipefail
cd "$(dirname "$0")/.."

[ $# -eq 1 ] || { echo "usage: scripts/cross-check.sh TARGET   (TARGET: aarch64)" >&2; exit 2; }
TARGET=$1
case "$TARGET" in
  aarch64) QEMU=qemu-aarch64 ;;
  *) echo "cross-check.sh: unknown target '$TARGET' (known: aarch64)" >&2; exit 2 ;;
esac
SYSROOT=build-$TARGET/sysroot
CROSS_BIN=build-$TARGET/app/cellsight
if [ ! -x "$CROSS_BIN" ] || [ ! -d "$SYSROOT" ]; then
  echo "cross-check.sh: no $CROSS_BIN or $SYSROOT: run scripts/cross-build.sh $TARGET first" >&2
  exit 2
fi
if ! command -v "$QEMU" >/dev/null; then
  echo "cross-check.sh: no $QEMU (scripts/cross-build.sh installs qemu-user)" >&2
  exit 2
fi

NATIVE_BIN=${CELLSIGHT_BIN:-build/app/cellsight}
if [ ! -x "$NATIVE_BIN" ]; then
  echo "== building the native cellsight (Release)"
  cmake -S . -B build -DCMAKE_BUILD_TYPE=Release >/dev/null
  cmake --build build -j"$(nproc)" --target cellsight
fi
NATIVE_BIN=$(realpath "$NATIVE_BIN")
WORK=${WORK:-out/cross-check-$TARGET}
rm -rf "$WORK"
mkdir -p "$WORK/scans"
WORK=$(realpath "$WORK")
CONFIG=$WORK/cellsight.yaml
CAL=$WORK/calibration/calibration.yaml
PARTS=(plate_4h plate_5h ribbed_v4 ribbed_v3)  # two look-alike pairs: a wrong pose or decision shows
SCANNED=(plate_5h ribbed_v4 ribbed_v3)
COUNT=5
START=$SECONDS
step() { echo "== $1 [at $((SECONDS - START)) s]"; }
native() { "$NATIVE_BIN" --config "$CONFIG" "$@"; }
cross() { "$QEMU" -L "$SYSROOT" "$CROSS_BIN" --config "$CONFIG" "$@"; }

cat >"$CONFIG" <<EOF
# Site file of scripts/cross-check.sh: only what differs from the built-in defaults.
sim:
  catalogue: $(realpath config/parts.yaml)
cascade:
  verify_budget_ms: 3000
  search_budget_ms: 3000
runtime:
  deadline_ms: 60000
EOF

step "1. help and sim --list: native and $TARGET under $QEMU"
for mode in help "sim --list"; do
  # shellcheck disable=SC2086  # the mode's words
  native $mode >"$WORK/native-${mode// /-}.txt"
  # shellcheck disable=SC2086
  cross $mode >"$WORK/$TARGET-${mode// /-}.txt"
  diff -u "$WORK/native-${mode// /-}.txt" "$WORK/$TARGET-${mode// /-}.txt" ||
    { echo "cross-check.sh: '$mode' differs between the native and the $TARGET binary" >&2; exit 1; }
  echo "   $mode: the same $(wc -l <"$WORK/native-${mode// /-}.txt") lines"
done

step "2. native: calibrating, teaching ${PARTS[*]} ($COUNT passes each), training"
CELLSIGHT_BIN=$NATIVE_BIN scripts/calibrate.sh --sim --config "$CONFIG" --work "$WORK/calibration" \
  --calibration "$CAL" >"$WORK/calibrate.log" 2>&1 || { cat "$WORK/calibrate.log" >&2; exit 1; }
id=1
for part in "${PARTS[@]}"; do
  native --models "$WORK/models" teach --part "$part" --id "$id" --sim --count "$COUNT" --calibration "$CAL" \
    >>"$WORK/teach.log" 2>&1 || { tail -n 20 "$WORK/teach.log" >&2; exit 1; }
  id=$((id + 1))
done
native --models "$WORK/models" train --calibration "$CAL" >"$WORK/train.log" 2>&1 ||
  { tail -n 20 "$WORK/train.log" >&2; exit 1; }
scans=()
seed=5001
for part in "${SCANNED[@]}"; do
  native scan --sim --part "$part" --seed "$seed" --out "$WORK/scans/$part-$seed.ply" --calibration "$CAL" \
    2>>"$WORK/scan.log"
  scans+=("$WORK/scans/$part-$seed.ply")
  seed=$((seed + 1))
done

step "3. classify --json: native, then $TARGET under $QEMU with a copy of the database"
native --models "$WORK/models" classify --json --calibration "$CAL" "${scans[@]}" >"$WORK/native.jsonl" \
  2>"$WORK/native-classify.log"
cp -a "$WORK/models" "$WORK/models-$TARGET"
cross --models "$WORK/models-$TARGET" classify --json --calibration "$CAL" "${scans[@]}" >"$WORK/$TARGET.jsonl" \
  2>"$WORK/$TARGET-classify.log"

python3 - "$WORK/native.jsonl" "$WORK/$TARGET.jsonl" "$TARGET" <<'EOF'
import json
import sys

TOLERANCE = {"x": 1e-6, "y": 1e-6, "z": 1e-6, "theta_deg": 1e-3, "rx_deg": 1e-3, "ry_deg": 1e-3}  # m, deg
# classify prints 6 significant digits: two values a tolerance apart in print may differ by a rounding error more
ROUNDING = 1e-12
native = [json.loads(line) for line in open(sys.argv[1])]
cross = [json.loads(line) for line in open(sys.argv[2])]
target = sys.argv[3]
failures = []
if len(native) != len(cross):
    failures.append(f"{len(native)} native decisions, {len(cross)} {target} decisions")


def pose_text(p):
    if p is None:
        return "no pose"
    return " ".join(f"{k} {p[k]}" if p[k] is not None else f"{k} -" for k in TOLERANCE)


for n, c in zip(native, cross):
    scan = n["scan"].rsplit("/", 1)[-1]
    print(f"   {scan}")
    for who, d in (("native", n), (target, c)):
        print(f"     {who:8} {d['status']:8} {d['class']} id {d['id']} (verified {d['verified']}, {d['ms']} ms): "
              f"{pose_text(d['pose'])}")
    for key in ("status", "class", "id"):
        if n[key] != c[key]:
            failures.append(f"{scan}: {key} {n[key]} (native) != {c[key]} ({target})")
    if (n["pose"] is None) != (c["pose"] is None):
        failures.append(f"{scan}: pose {n['pose']} (native) != {c['pose']} ({target})")
    elif n["pose"] is not None:
        for key, tol in TOLERANCE.items():
            a, b = n["pose"][key], c["pose"][key]
            if (a is None) != (b is None) or (a is not None and abs(a - b) > tol + ROUNDING):
                failures.append(f"{scan}: pose {key} {a} (native) != {b} ({target}), tolerance {tol}")
if failures:
    print("FAIL: " + "; ".join(failures))
    sys.exit(1)
print(f"PASS: {len(native)} scans, the same decisions; poses within 1 um and 0.001 deg")
EOF
step "done: $WORK"
