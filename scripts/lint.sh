#!/usr/bin/env bash
# The code rules that CI checks (issue 12; a stage of scripts/test.sh, CELLSIGHT_LINT=0 skips it there):
#   1. format  clang-format (.clang-format) in check mode: first the files changed since $CELLSIGHT_LINT_BASE
#              (default origin/main, when that ref exists), then every tracked .cpp/.hpp
#   2. size    scripts/check_size.py: no file under app/, runtime/, cli/ over 600 lines, no function outside
#              tests/ over 100 lines
#   3. names   scripts/check_test_names.py: no ';' in a Catch2 test name (ctest would split it and run nothing)
#   4. tidy    clang-tidy (.clang-tidy) on the pure and real-time layers, algo/ and runtime/, every finding an
#              error; a clang compile database configured (not built) in $CELLSIGHT_LINT_BUILD (build-lint)
# Usage: scripts/lint.sh [format|size|names|tidy]...   (default: all four). Exit 1 when a rule is broken; every
# stage runs, so one run shows every finding.
set -euo pipefail
cd "$(dirname "$0")/.."

stages=("$@")
[ ${#stages[@]} -gt 0 ] || stages=(format size names tidy)
BUILD=${CELLSIGHT_LINT_BUILD:-build-lint}
TIDY_DIRS=(algo runtime)
failed=()

mapfile -t all_files < <(git ls-files '*.cpp' '*.hpp')

check_format() {
  local base=${CELLSIGHT_LINT_BASE:-origin/main} changed=()
  if git rev-parse -q --verify "$base^{commit}" >/dev/null; then
    mapfile -t changed < <(git diff --name-only --diff-filter=d "$base" -- '*.cpp' '*.hpp')
    if [ ${#changed[@]} -gt 0 ] && ! clang-format --dry-run --Werror "${changed[@]}"; then
      echo "lint: format: files changed since $base deviate from .clang-format (fix: clang-format -i FILE)" >&2
      return 1
    fi
  fi
  # One clang-format for all files (2 s in a clean run here); a process per file took 85 s, mostly start-up. Only
  # when that finds something is every file asked alone, to name the ones that deviate.
  if clang-format --dry-run --Werror "${all_files[@]}" >/dev/null 2>&1; then
    echo "lint: format: ${#all_files[@]} files match .clang-format"
    return 0
  fi
  local bad=()
  for f in "${all_files[@]}"; do
    clang-format --dry-run --Werror "$f" >/dev/null 2>&1 || bad+=("$f")
  done
  if [ ${#bad[@]} -gt 0 ]; then
    clang-format --dry-run "${bad[@]:0:3}" 2>&1 | head -n 30
    echo "lint: format: ${#bad[@]} of ${#all_files[@]} files deviate from .clang-format: ${bad[*]}" >&2
    echo "lint: format: fix with clang-format -i FILE..." >&2
    return 1
  fi
  echo "lint: format: ${#all_files[@]} files match .clang-format"
}

check_tidy() {
  CC=clang CXX=clang++ cmake -S . -B "$BUILD" -DCMAKE_BUILD_TYPE=Release -DCMAKE_EXPORT_COMPILE_COMMANDS=ON \
    >/dev/null
  local dirs=() d
  for d in "${TIDY_DIRS[@]}"; do [ -d "$d" ] && dirs+=("$d"); done
  local regex
  regex="^$(pwd)/($(IFS='|'; echo "${dirs[*]}"))/.*\\.cpp\$"
  # run-clang-tidy: one clang-tidy per translation unit, in parallel. Version 14 (Debian 12) has no
  # -warnings-as-errors (it stops at the unknown option), exits 0 on warnings and always colours its output: so a
  # finding is a "warning:" or "error:" line of the log with the colour codes taken out, and a non-zero exit (a file
  # that did not compile) fails the stage too.
  local rc=0
  run-clang-tidy -p "$BUILD" -j "$(nproc)" -quiet -extra-arg=-fno-color-diagnostics "$regex" 2>&1 |
    sed 's/\x1b\[[0-9;]*m//g' >"$BUILD/clang-tidy.log" || rc=$?
  if [ "$rc" -ne 0 ] || grep -q -E '(warning|error):' "$BUILD/clang-tidy.log"; then
    grep -E -A4 '(warning|error):' "$BUILD/clang-tidy.log" | grep -v '^Suppressed' | head -n 120
    echo "lint: tidy: findings in ${dirs[*]} (whole output in $BUILD/clang-tidy.log)" >&2
    return 1
  fi
  echo "lint: tidy: no findings in ${dirs[*]}"
}

for stage in "${stages[@]}"; do
  start=$SECONDS
  case $stage in
    format) check_format || failed+=(format) ;;
    size) python3 scripts/check_size.py "${all_files[@]}" || failed+=(size) ;;
    names) python3 scripts/check_test_names.py $(git ls-files 'tests/*.cpp') || failed+=(names) ;;
    tidy) check_tidy || failed+=(tidy) ;;
    *) echo "lint: unknown stage '$stage' (format, size, names, tidy)" >&2; exit 2 ;;
  esac
  echo "lint: $stage took $((SECONDS - start)) s"
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "lint: FAILED: ${failed[*]}" >&2
  exit 1
fi
