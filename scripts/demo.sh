#!/usr/bin/env bash
# The main command (README): installs what is missing, builds cellsight (Release) and runs it on the simulated
# cell — no hardware needed. Today: one simulated pass of a catalogue part rendered to out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."

scripts/setup.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build build -j"$(nproc)" --target cellsight

PART=${1:-ribbed_v4}
SEED=${2:-1}
OUT=out/demo-$PART-$SEED
rm -rf "$OUT"
mkdir -p out
./build/app/cellsight sim --list
./build/app/cellsight sim --part "$PART" --seed "$SEED" --out "$OUT"
echo "demo: $(ls "$OUT/frames" | wc -l) frames in $OUT/frames, ground truth in $OUT/truth.yaml"
