#!/usr/bin/env bash
# The ThreadSanitizer stage of the test command (scripts/test.sh). Usage: scripts/tsan.sh [REGEX]: the threaded test
# binaries (all, or those REGEX matches) built with CELLSIGHT_TSAN=ON in $CELLSIGHT_TSAN_BUILD (build-tsan) and run
# one at a time; exit 1 on a report or a failed test.
set -euo pipefail
cd "$(dirname "$0")/.."

# The tests with threads: the production loop's loop and recognition threads with the Modbus network thread and the
# `run` mode (test_run_loop, test_modbus), the loop's rooms on their own (the recognition worker's futex mailbox,
# the log queue and its writer thread, the pass acquirer), the encoder's decoding thread (test_gpio) and the
# training's worker threads (test_recognition "[training]"). A data race or a lock-order inversion fails the stage.
# Own build folder: TSan cannot share a process with ASan. Suppressions (scripts/tsan-suppressions.txt) only for
# reports inside libraries we do not build (GDAL under OpenCV's PNG encoder); every report in our code is a bug.
TSAN_TESTS=(test_run_loop test_recognition_worker test_log_queue test_pass_acquirer test_modbus test_gpio test_recognition)
TSAN=${CELLSIGHT_TSAN_BUILD:-build-tsan}
selected=()
for t in "${TSAN_TESTS[@]}"; do
  if [ $# -eq 0 ] || [[ $t =~ $1 ]]; then selected+=("$t"); fi
done
if [ ${#selected[@]} -gt 0 ]; then
  cmake -S . -B "$TSAN" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCELLSIGHT_TSAN=ON -DCELLSIGHT_WERROR=ON >/dev/null
  cmake --build "$TSAN" -j"$(nproc)" --target "${selected[@]}"
  export TSAN_OPTIONS=${TSAN_OPTIONS:-halt_on_error=1 second_deadlock_stack=1 suppressions=$PWD/scripts/tsan-suppressions.txt}
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
