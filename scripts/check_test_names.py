#!/usr/bin/env python3
"""No Catch2 test name with a ';' (a stage of scripts/lint.sh).

catch_discover_tests registers every TEST_CASE as a ctest test by its name, and CMake splits lists at ';': a name
with one became two ctest tests whose filters match no test case, so Catch ran nothing and exited 0 ("No tests ran")
- 26 test cases had never run in CI when this was found. Names are read the way the compiler joins them: the
adjacent string literals of TEST_CASE's first argument.

usage: scripts/check_test_names.py FILE.cpp...   exit 1 when a name has a ';' (each one printed with file and line)
"""
import re
import sys

NAME = re.compile(r'(?:TEST_CASE|SCENARIO)\(\s*((?:"(?:[^"\\]|\\.)*"\s*)+)')
LITERAL = re.compile(r'"((?:[^"\\]|\\.)*)"')


def main(paths):
    bad = 0
    for path in paths:
        with open(path, encoding="utf-8") as f:
            text = f.read()
        for m in NAME.finditer(text):
            name = "".join(LITERAL.findall(m.group(1)))
            if ";" in name:
                line = text.count("\n", 0, m.start()) + 1
                print(f"{path}:{line}: test name has a ';' (ctest would split it and run nothing): {name}",
                      file=sys.stderr)
                bad += 1
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
