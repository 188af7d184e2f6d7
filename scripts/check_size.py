#!/usr/bin/env python3
"""The size rules of issue 12, checked by scripts/lint.sh: no file under app/, runtime/ or cli/ over 600 lines and
no C++ function over 100 lines outside tests/ (lines from the line of the body's opening brace to the closing
brace's). Usage: scripts/check_size.py [FILE...] (default: every tracked .cpp/.hpp). Exit 1 on a violation.

Written here rather than taken from a tool: lizard or clang-query would count the same, but neither is a Debian 12
package the project already needs, and a brace matcher over comment- and string-stripped text is enough for our
code (no macros that open bodies). A body is a '{' whose head ends in a parameter list ')' (with qualifiers,
a trailing return type or a constructor's initialiser list) outside any other function body; lambdas and blocks
inside a body count as part of it.
"""
import pathlib
import re
import subprocess
import sys

FILE_LIMIT = 600
FILE_LIMIT_DIRS = ('app/', 'runtime/', 'cli/', 'hmi/')
FUNCTION_LIMIT = 100

def blank(text):
    """The text with every character but newlines replaced by a space (line numbers stay right)."""
    return re.sub(r'[^\n]', ' ', text)


def strip_comments_and_literals(src):
    """Comments, string and character literals (raw strings included) blanked out, so their braces do not count."""
    out = []
    i, n = 0, len(src)
    while i < n:
        if src.startswith('//', i):
            j = src.find('\n', i)
            j = n if j < 0 else j
        elif src.startswith('/*', i):
            j = src.find('*/', i + 2)
            j = n if j < 0 else j + 2
        elif (m := re.match(r'R"([^(\s]*)\(', src[i:i + 20])) and (i == 0 or not src[i - 1].isalnum()):
            end = ')' + m.group(1) + '"'
            j = src.find(end, i)
            j = n if j < 0 else j + len(end)
        elif src[i] in '"\'' and not (src[i] == "'" and i > 0 and src[i - 1].isalnum()):  # 1'000 is a digit separator
            quote, j = src[i], i + 1
            while j < n and src[j] != quote:
                j += 2 if src[j] == '\\' else 1
            j += 1
        else:
            out.append(src[i])
            i += 1
            continue
        out.append(blank(src[i:j]))
        i = j
    return ''.join(out)


# What may stand between a parameter list's ')' and the body's '{': qualifiers, a trailing return type, a
# constructor's initialiser list.
FUNCTION_HEAD = re.compile(r'\)\s*(const|noexcept|override|final|mutable|\s|->\s*[\w:<>,\s*&]+|:\s*[^;{}]*)*$')
TYPE_HEAD = re.compile(r'\b(namespace|class|struct|enum|union)\b[^;{}()]*$')
CONTROL = ('if', 'for', 'while', 'switch', 'catch', 'return')


def function_name(head):
    """The name before the parameter list that ends `head` (None for a control statement or no name)."""
    close = head.rfind(')')
    depth, j = 0, close
    while j >= 0:
        if head[j] == ')':
            depth += 1
        elif head[j] == '(':
            depth -= 1
            if depth == 0:
                break
        j -= 1
    m = re.search(r'(operator\S+|[~\w:]+(?:<[^<>]*>)?)\s*$', head[:j]) if j > 0 else None
    if not m or m.group(1) in CONTROL:
        return None
    return m.group(1)


def functions(path):
    """(lines, first line, name) of every function body in the file at namespace or class level."""
    text = strip_comments_and_literals(pathlib.Path(path).read_text(encoding='utf-8', errors='replace'))
    found, open_blocks = [], []  # open_blocks: (is_function, first line, name)
    line = 1
    for i, c in enumerate(text):
        if c == '\n':
            line += 1
        elif c == '{':
            name = None
            if not any(is_fn for is_fn, _, _ in open_blocks):
                head = text[max(0, i - 400):i].rstrip()
                if FUNCTION_HEAD.search(head) and not TYPE_HEAD.search(head):
                    name = function_name(head)
            open_blocks.append((name is not None, line, name))
        elif c == '}' and open_blocks:
            is_fn, start, name = open_blocks.pop()
            if is_fn:
                found.append((line - start + 1, start, name))
    return found


def main():
    files = sys.argv[1:] or subprocess.run(['git', 'ls-files', '*.cpp', '*.hpp'], capture_output=True, text=True,
                                           check=True).stdout.split()
    bad = []
    for p in files:
        if p.startswith('tests/') or not pathlib.Path(p).is_file():
            continue
        lines = pathlib.Path(p).read_text(encoding='utf-8', errors='replace').count('\n')
        if p.startswith(FILE_LIMIT_DIRS) and lines > FILE_LIMIT:
            bad.append(f'{p}: {lines} lines (limit {FILE_LIMIT} under {", ".join(FILE_LIMIT_DIRS)})')
        for n, start, name in functions(p):
            if n > FUNCTION_LIMIT:
                bad.append(f'{p}:{start}: function {name} has {n} lines (limit {FUNCTION_LIMIT})')
    for b in bad:
        print(b)
    print(f'check_size: {len(files)} files, {len(bad)} over the limits')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
