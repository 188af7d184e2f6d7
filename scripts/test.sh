#!/usr/bin/env bash
# The test command (README): installs what is missing, builds with AddressSanitizer + UndefinedBehaviorSanitizer
# and warnings as errors, and runs every test with ctest, then the timing-sensitive tests in a Release build, the
# threaded tests under ThreadSanitizer ($CELLSIGHT_TSAN=0 skips), the soak (scripts/soak.sh --ci: 500 parts with
# faults injected; CELLSIGHT_SOAK=0 skips it), then every fuzz target for a few seconds (scripts/fuzz.sh;
# $CELLSIGHT_FUZZ_SECONDS each, 0 skips). Usage: scripts/test.sh [regex]: the ctest tests, test binaries and fuzz
# targets it matches ("soak" also matches the soak)
set -euo pipefail
cd "$(dirname "$0")/.."

scripts/setup.sh
BUILD=${CELLSIGHT_TEST_BUILD:-build-test}
cmake -S . -B "$BUILD" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCELLSIGHT_SANITIZE=ON -DCELLSIGHT_WERROR=ON >/dev/null
cmake --build "$BUILD" -j"$(nproc)"
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=1}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
if [ $# -gt 0 ]; then
  ctest --test-dir "$BUILD" --output-on-failure -j"$(nproc)" -R "$1"
else
  ctest --test-dir "$BUILD" --output-on-failure -j"$(nproc)"
fi
# The timing-sensitive tests (the loop's deadlines and hand-offs, the Modbus server) run in a Release build as well:
# the sanitizers slow the code 2-5 times, which once hid tests that passed only while the loop was slow (issue 15).
RELEASE_TESTS=(test_run_loop test_modbus)
RELEASE=${CELLSIGHT_RELEASE_BUILD:-build-test-release}
selected=()
for t in "${RELEASE_TESTS[@]}"; do
  if [ $# -eq 0 ] || [[ $t =~ $1 ]]; then selected+=("$t"); fi
done
if [ ${#selected[@]} -gt 0 ]; then
  # (Warnings are not errors here: the sanitizer build above holds that line, and GCC 12 at -O3 reports false
  # -Warray-bounds / -Wrestrict in libstdc++'s vector and string code, e.g. test_modbus.cpp's frame building.)
  cmake -S . -B "$RELEASE" -DCMAKE_BUILD_TYPE=Release -DCELLSIGHT_WERROR=OFF >/dev/null
  cmake --build "$RELEASE" -j"$(nproc)" --target "${selected[@]}"
  regex=$(IFS='|'; echo "${selected[*]}")
  ctest --test-dir "$RELEASE" --output-on-failure -j"$(nproc)" -R "^($regex):"
fi
# The tests with threads run again under ThreadSanitizer: the production loop's loop and recognition threads with the
# Modbus network thread and the `run` mode (test_run_loop, test_modbus), the encoder's decoding thread (test_gpio) and
# the training's worker threads (test_recognition "[training]"). A data race or a lock-order inversion fails the
# stage; CELLSIGHT_TSAN=0 skips it. Own build folder: TSan cannot share a process with ASan. No suppressions: every
# report in our code is a bug to fix, and none of these tests reaches one inside a library.
TSAN_TESTS=(test_run_loop test_modbus test_gpio test_recognition)
TSAN=${CELLSIGHT_TSAN_BUILD:-build-tsan}
selected=()
if [ "${CELLSIGHT_TSAN:-1}" != 0 ]; then
  for t in "${TSAN_TESTS[@]}"; do
    if [ $# -eq 0 ] || [[ $t =~ $1 ]]; then selected+=("$t"); fi
  done
fi
if [ ${#selected[@]} -gt 0 ]; then
  cmake -S . -B "$TSAN" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCELLSIGHT_TSAN=ON -DCELLSIGHT_WERROR=ON >/dev/null
  cmake --build "$TSAN" -j"$(nproc)" --target "${selected[@]}"
  export TSAN_OPTIONS=${TSAN_OPTIONS:-halt_on_error=1 second_deadlock_stack=1}
  failed=()
  # One binary at a time: TSan slows the code 5-15 times, and the loop's deadlines are real time.
  for t in "${selected[@]}"; do
    filter=()
    [ "$t" = test_recognition ] && filter=("[training]")  # its other cases have no threads
    log="$TSAN/tests/$t.tsan.log"             # what the test and TSan print
    report="$TSAN/tests/$t.tsan-report.txt"   # Catch's report: the failed assertions and the totals
    start=$SECONDS
    # In the binary's folder, as ctest runs it.
    if (cd "$TSAN/tests" && timeout 900 "./$t" "${filter[@]}" -o "$t.tsan-report.txt") >"$log" 2>&1; then
      echo "tsan: $t: $(grep -E '^All tests passed' "$report") ($((SECONDS - start)) s)"
    else
      rc=$?
      failed+=("$t")
      echo "tsan: $t FAILED with exit code $rc after $((SECONDS - start)) s (output in $log, report in $report):"
      if grep -q 'WARNING: ThreadSanitizer' "$log"; then
        sed -n '/WARNING: ThreadSanitizer/,$p' "$log" | head -n 150
      else
        cat "$report" 2>/dev/null || true
        tail -n 20 "$log"
      fi
    fi
  done
  if [ ${#failed[@]} -gt 0 ]; then
    echo "tsan: FAILED: ${failed[*]}" >&2
    exit 1
  fi
fi
# The soak (README "Soak and fault injection"): `run --sim` for 500 parts in the Release build with an acknowledging
# PLC, a polling client, an abusive one and faults injected, SIGTERM mid-pass and a teach into a full disk; about
# 2 minutes here.
if [ "${CELLSIGHT_SOAK:-1}" != 0 ] && { [ $# -eq 0 ] || [[ soak =~ $1 ]]; }; then
  CELLSIGHT_SOAK_BUILD=$RELEASE scripts/soak.sh --ci --work "$RELEASE/soak"
fi
scripts/fuzz.sh --ci "${CELLSIGHT_FUZZ_SECONDS:-10}" "$@"
