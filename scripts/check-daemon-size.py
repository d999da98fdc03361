#!/usr/bin/env python3
"""Sizes of daemon/ (issue 21): no source file over 600 lines, no function over 100 lines.

Usage: scripts/check-daemon-size.py [--max-file 600] [--max-function 100] [--top N] [DIR...]

Prints the longest files and functions and exits 1 when a limit is exceeded. Functions are found
by their braces in the source with comments, string and character literals blanked out: a
function is a brace block opened at namespace or class level whose head ends with `)` (plus
qualifiers such as const, noexcept, override, a trailing return type or a constructor's member
initialisers). A lambda or local class inside a function counts as part of that function, as it
does for a reader. Lines are counted from the head's first line to the closing brace.
"""
import argparse
import pathlib
import re
import sys

SOURCE_SUFFIXES = {".cpp", ".hpp", ".in"}


def blank_literals(text):
    """Comments, strings and character literals replaced by spaces (newlines kept)."""
    out = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            j = text.find("*/", i + 2)
            j = n if j < 0 else j + 2
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "R" and text.startswith('R"', i) and (i == 0 or not (text[i - 1].isalnum() or text[i - 1] == "_")):
            m = re.match(r'R"([^(\s]*)\(', text[i:])
            if not m:
                out.append(c)
                i += 1
                continue
            end = text.find(")" + m.group(1) + '"', i + m.end())
            end = n if end < 0 else end + len(m.group(1)) + 2
            out.append(re.sub(r"[^\n]", " ", text[i:end]))
            i = end
        elif c in "\"'":
            if c == "'" and i > 0 and text[i - 1].isalnum():  # digit separator 1'000
                out.append(" ")
                i += 1
                continue
            j = i + 1
            while j < n and text[j] != c and text[j] != "\n":
                j += 2 if text[j] == "\\" else 1
            out.append(" " * (min(j + 1, n) - i))
            i = j + 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


HEAD_END = re.compile(
    r"\)\s*(const|noexcept|override|final|mutable|&|&&|\s|->\s*[\w:<>,\s*&]+|noexcept\s*\([^)]*\))*$|"
    r"\)\s*:\s*[\w:]+[({].*$",  # constructor with member initialisers
    re.S,
)
NOT_FUNCTION = re.compile(r"^\s*(if|for|while|switch|catch|return)\b|=\s*$|\]\s*\(.*\)\s*(mutable\s*)?(->.*)?$")


def functions(path):
    text = blank_literals(path.read_text(errors="replace"))
    lines = text.split("\n")
    result = []
    # stack of (kind, start_line, name): kind in namespace, class, function, block
    stack = []
    head = ""
    head_line = 0
    for lineno, line in enumerate(lines, 1):
        stripped = line.strip()
        if stripped.startswith("#"):
            continue
        for ch in line:
            if ch == "{":
                h = head.strip()
                inside_function = any(k == "function" for k, _, _ in stack)
                if inside_function:
                    kind = "block"
                elif re.match(r"^(extern\s+\"C\"\s*)?namespace\b|^extern\b", h) or h == "":
                    kind = "namespace" if h.startswith("namespace") or h == "" else "block"
                elif re.search(r"\b(class|struct|union|enum)\b[^()]*$", h):
                    kind = "class"
                elif HEAD_END.search(h) and not NOT_FUNCTION.search(h) and "(" in h:
                    kind = "function"
                else:
                    kind = "block"
                name = re.sub(r"\s+", " ", h)[:90]
                stack.append((kind, head_line or lineno, name))
                head = ""
                head_line = 0
            elif ch == "}":
                if stack:
                    kind, start, name = stack.pop()
                    if kind == "function":
                        result.append((lineno - start + 1, start, name))
                head = ""
                head_line = 0
            elif ch == ";":
                head = ""
                head_line = 0
            else:
                if not head.strip() and not ch.isspace():
                    head_line = lineno
                head += ch
        head += "\n"
        # a label such as `public:` or `case X:` ends nothing, but access specifiers start heads
        if re.match(r"^\s*(public|private|protected)\s*:\s*$", line):
            head = ""
            head_line = 0
    return result


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--max-file", type=int, default=600)
    ap.add_argument("--max-function", type=int, default=100)
    ap.add_argument("--top", type=int, default=10)
    ap.add_argument("dirs", nargs="*", default=["daemon"])
    args = ap.parse_args()
    files = sorted(p for d in args.dirs for p in pathlib.Path(d).rglob("*")
                   if p.is_file() and p.suffix in SOURCE_SUFFIXES)
    sizes = sorted(((len(p.read_text(errors="replace").splitlines()), p) for p in files), reverse=True)
    funcs = sorted(((n, str(p), start, name) for p in files if p.suffix != ".in"
                    for n, start, name in functions(p)), reverse=True)
    print(f"{len(files)} files, {sum(n for n, _ in sizes)} lines; {len(funcs)} functions")
    print(f"longest files (limit {args.max_file}):")
    for n, p in sizes[: args.top]:
        print(f"  {n:5d}  {p}")
    print(f"longest functions (limit {args.max_function}):")
    for n, p, start, name in funcs[: args.top]:
        print(f"  {n:5d}  {p}:{start}  {name}")
    bad_files = [p for n, p in sizes if n > args.max_file]
    bad_funcs = [(p, s) for n, p, s, _ in funcs if n > args.max_function]
    print(f"files over {args.max_file}: {len(bad_files)}; functions over {args.max_function}: {len(bad_funcs)}")
    return 1 if bad_files or bad_funcs else 0


if __name__ == "__main__":
    sys.exit(main())
