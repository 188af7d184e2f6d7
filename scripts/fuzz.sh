#!/usr/bin/env bash
# Builds the libFuzzer targets (tests/fuzz, clang, ASan+UBSan) in build-fuzz and runs each for SECONDS (README
# "Fuzzing"). Usage:
#   scripts/fuzz.sh [SECONDS=600] [TARGET...]   every target (or the named ones) for SECONDS each (0: until Ctrl-C)
#   scripts/fuzz.sh --ci SECONDS [REGEX]          the test command's stage: the targets REGEX matches, seeds only,
#                                                 nothing kept; SECONDS 0 skips it
#   scripts/fuzz.sh --seeds                       rewrite tests/fuzz/corpus/ with the product's own writers
# A hand run keeps what it learns in out/fuzz/corpus/TARGET (reused by the next run); a crash, leak, timeout or
# oversized allocation leaves its input in out/fuzz/artifacts/ and makes the script fail. Reproduce one with
#   build-fuzz/tests/fuzz/TARGET out/fuzz/artifacts/TARGET-crash-...
set -euo pipefail
cd "$(dirname "$0")/.."

TARGETS=(fuzz_ply fuzz_scan_file fuzz_config fuzz_template fuzz_svm fuzz_manifest fuzz_modbus_request)
BUILD=${CELLSIGHT_FUZZ_BUILD:-build-fuzz}
# Limits every target must stay within: a reader answers a small file quickly and in proportion to its size.
LIMITS=(-timeout=10 -rss_limit_mb=2048 -malloc_limit_mb=256 -max_len=16384)

build() {
  CC=clang CXX=clang++ cmake -S . -B "$BUILD" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCELLSIGHT_FUZZ=ON \
    -DCELLSIGHT_WERROR=ON >/dev/null
  cmake --build "$BUILD" -j"$(nproc)" --target "$@"
}

mode=run
if [ "${1:-}" = --seeds ]; then
  build make_fuzz_seeds
  "$BUILD/tests/fuzz/make_fuzz_seeds" tests/fuzz/corpus
  mkdir -p tests/fuzz/corpus/fuzz_config
  cp config/cellsight.yaml tests/fuzz/corpus/fuzz_config/cellsight.yaml
  exit 0
elif [ "${1:-}" = --ci ]; then
  mode=ci
  shift
fi
SECONDS_EACH=${1:-600}
shift || true
selected=()
if [ "$mode" = ci ]; then
  for t in "${TARGETS[@]}"; do
    if [ $# -eq 0 ] || [[ $t =~ $1 ]]; then selected+=("$t"); fi
  done
else
  selected=("${@:-${TARGETS[@]}}")
fi
[ ${#selected[@]} -gt 0 ] || exit 0
if [ "$mode" = ci ] && [ "$SECONDS_EACH" = 0 ]; then exit 0; fi

build "${selected[@]}"
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
mkdir -p out/fuzz/artifacts
failed=()
for t in "${selected[@]}"; do
  if [ "$mode" = ci ]; then
    work=$(mktemp -d)
  else
    work=out/fuzz/corpus/$t
    mkdir -p "$work"
  fi
  echo "fuzz: $t for ${SECONDS_EACH} s"
  if ! "$BUILD/tests/fuzz/$t" "${LIMITS[@]}" -max_total_time="$SECONDS_EACH" -print_final_stats=1 \
      -artifact_prefix="out/fuzz/artifacts/$t-" "$work" "tests/fuzz/corpus/$t" 2>"out/fuzz/$t.log"; then
    failed+=("$t")
    tail -n 40 "out/fuzz/$t.log"
  fi
  grep -E '^(Done|stat::number_of_executed_units|stat::peak_rss_mb)' "out/fuzz/$t.log" | tr '\n' ' ' | sed 's/^/  /'
  echo
  if [ "$mode" = ci ]; then rm -rf "$work"; fi
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "fuzz: FAILED: ${failed[*]} (inputs in out/fuzz/artifacts/, logs in out/fuzz/)" >&2
  exit 1
fi
