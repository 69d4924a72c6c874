#!/usr/bin/env python3
"""The layers as docs/architecture.md draws them, checked on the tree (issue 37).

Reads two tables from docs/architecture.md, between `<!-- layers:begin -->` and
`<!-- layers:end -->` and between `<!-- long-functions:begin -->` and `<!-- long-functions:end -->`:

  | folder | may include | may not include |
  the project folders (or files) a folder's sources may `#include "..."`: `common/mesh` is that
  folder only, `server/models/**` that folder and every folder below it, `common/app/log.h` one
  file; and system headers a folder may not `#include <...>` (a prefix: `dds/` is every Cyclone
  header, `fstream` the one). The row with the longest folder that holds a file governs it;
  a folder's own files are always allowed. Folders below `tests/`, `idl/` and the build tree are
  not checked.

  | file | function | lines | why |
  the functions allowed over MAX_FUNCTION_LINES, with the reason.

and fails (exit 1), printing every violation as FILE:LINE: message, on:
  - an #include the table does not allow, or a source file in no row of the table;
  - a source file in common/, server/, haptic_node/ or viewer/ over MAX_FILE_LINES lines;
  - a function over MAX_FUNCTION_LINES lines not in the long-functions table (or longer than the
    table says).

Usage: check_structure.py [ROOT]   (default: the checkout this script is in)
"""
import os
import re
import sys

MAX_FILE_LINES = 900
MAX_FUNCTION_LINES = 150
CHECKED_TOP = ("common", "server", "haptic_node", "viewer")
SOURCE_EXT = (".h", ".cc", ".c")


def read_table(doc, name):
    m = re.search(r"<!-- %s:begin -->(.*?)<!-- %s:end -->" % (name, name), doc, re.S)
    if not m:
        raise SystemExit("check_structure: docs/architecture.md has no <!-- %s:begin --> table" % name)
    rows = []
    for line in m.group(1).splitlines():
        line = line.strip()
        if not line.startswith("|") or set(line) <= set("|-: "):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0].lower() in ("folder", "file"):
            continue  # the header
        rows.append(cells)
    return rows


def names(cell):
    """`a`, `b/**` ... in a cell (backquoted), or none for '—'."""
    return re.findall(r"`([^`]+)`", cell)


def load_layers(doc):
    layers = {}
    for cells in read_table(doc, "layers"):
        if len(cells) < 3:
            raise SystemExit("check_structure: a layers row needs 3 cells: %s" % cells)
        for folder in names(cells[0]):
            layers[folder.rstrip("/")] = (names(cells[1]), names(cells[2]))
    return layers


def load_long_functions(doc):
    allowed = {}
    for cells in read_table(doc, "long-functions"):
        if len(cells) < 4:
            raise SystemExit("check_structure: a long-functions row needs 4 cells: %s" % cells)
        files, functions = names(cells[0]), names(cells[1])
        if not files or not functions or not cells[3]:
            raise SystemExit("check_structure: a long-functions row needs a file, a function "
                             "and a reason: %s" % cells)
        allowed[(files[0], functions[0])] = int(cells[2])
    return allowed


def row_for(layers, folder):
    best = None
    for f in layers:
        if folder == f or folder.startswith(f + "/"):
            if best is None or len(f) > len(best):
                best = f
    return best


def include_allowed(target, own_folder, allowed):
    target_folder = os.path.dirname(target)
    if target_folder == own_folder:
        return True
    for a in allowed:
        if a.endswith("/**"):
            base = a[:-3]
            if target_folder == base or target_folder.startswith(base + "/"):
                return True
        elif a.endswith((".h", ".hpp")):
            if target == a:
                return True
        elif target_folder == a:
            return True
    return False


def strip_comments_and_strings(text):
    """The text with comments, string and character literals blanked (newlines kept)."""
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
        elif c == 'R' and text.startswith('R"', i):
            m = re.match(r'R"([^(]*)\(', text[i:])
            if m:
                end = text.find(")" + m.group(1) + '"', i)
                j = n if end < 0 else end + len(m.group(1)) + 2
                out.append(re.sub(r"[^\n]", " ", text[i:j]))
                i = j
            else:
                out.append(c)
                i += 1
        elif c in "\"'":
            # A digit separator (1'000) is not a character literal.
            if c == "'" and i > 0 and text[i - 1].isalnum() and i + 1 < n and text[i + 1].isalnum():
                out.append(" ")
                i += 1
                continue
            j = i + 1
            while j < n and text[j] != c and text[j] != "\n":
                j += 2 if text[j] == "\\" else 1
            j = min(j + 1, n)
            out.append(c + " " * (j - i - 2) + c if j - i >= 2 else " " * (j - i))
            i = j
        else:
            out.append(c)
            i += 1
    return "".join(out)


CONTAINER = re.compile(
    r"(^|[\s;}])((namespace\b[^;{]*)|(extern\s+\"C\"\s*)|((class|struct|union|enum)\b[^;{()=]*))$")


def functions(text):
    """(name, first line, line count) of every function body at namespace or class scope."""
    code = strip_comments_and_strings(text)
    # Preprocessor lines do not open or close anything.
    code = re.sub(r"(?m)^[ \t]*#.*(?:\\\n.*)*$", lambda m: re.sub(r"[^\n]", " ", m.group(0)), code)
    found = []
    stack = []  # per open brace: 'container', 'function' or 'other'
    last_stmt_end = 0
    for i, c in enumerate(code):
        if c == "{":
            head = code[last_stmt_end:i].strip()
            inside_function = any(k == "function" for k, _ in stack)
            if inside_function:
                stack.append(("other", i))
            elif CONTAINER.search(" " + head) and "(" not in head.split("{")[-1].split("=")[0] \
                    or head.endswith(("=", "return")) or head == "":
                kind = "container" if CONTAINER.search(" " + head) else "other"
                stack.append((kind, i))
            elif ")" in head or head.endswith(("const", "noexcept", "override", "final")) \
                    or re.search(r"\)\s*(const|noexcept|override|final|->.*|:.*)?\s*$", head, re.S):
                start = last_stmt_end + (len(code[last_stmt_end:i]) - len(code[last_stmt_end:i].lstrip()))
                m = re.search(r"([~\w:]+(?:operator\s*\S+)?)\s*\(", head)
                name = m.group(1) if m else head[:40]
                stack.append(("function", (i, start, name)))
            else:
                stack.append(("other", i))
            last_stmt_end = i + 1
        elif c == "}":
            if stack:
                kind, data = stack.pop()
                if kind == "function":
                    _, start, name = data
                    first = code.count("\n", 0, start) + 1
                    last = code.count("\n", 0, i) + 1
                    found.append((name, first, last - first + 1))
            last_stmt_end = i + 1
        elif c == ";":
            if not any(k == "function" for k, _ in stack):
                last_stmt_end = i + 1
        elif c == ":" and not any(k == "function" for k, _ in stack):
            # access specifiers (public:) end a declaration's head; `::` and ctor-initialisers
            # do not.
            before = code[last_stmt_end:i].strip()
            if before in ("public", "private", "protected") and code[i + 1:i + 2] != ":":
                last_stmt_end = i + 1
    return found


def main():
    root = os.path.abspath(sys.argv[1] if len(sys.argv) > 1 else
                           os.path.join(os.path.dirname(__file__), "..", ".."))
    doc_path = os.path.join(root, "docs", "architecture.md")
    with open(doc_path, encoding="utf-8") as f:
        doc = f.read()
    layers = load_layers(doc)
    long_functions = load_long_functions(doc)
    problems = []
    seen_long = set()
    for top in CHECKED_TOP:
        for dirpath, _, files in os.walk(os.path.join(root, top)):
            for name in sorted(files):
                if not name.endswith(SOURCE_EXT):
                    continue
                path = os.path.join(dirpath, name)
                rel = os.path.relpath(path, root)
                folder = os.path.dirname(rel)
                with open(path, encoding="utf-8", errors="replace") as f:
                    text = f.read()
                lines = text.count("\n") + (0 if text.endswith("\n") else 1)
                if lines > MAX_FILE_LINES:
                    problems.append("%s:1: %d lines (at most %d)" % (rel, lines, MAX_FILE_LINES))
                row = row_for(layers, folder)
                if row is None:
                    problems.append("%s:1: folder %s is in no row of the layers table in "
                                    "docs/architecture.md" % (rel, folder))
                    continue
                allowed, forbidden = layers[row]
                for number, line in enumerate(text.splitlines(), 1):
                    m = re.match(r'\s*#\s*include\s*"([^"]+)"', line)
                    if m and not include_allowed(m.group(1), folder, allowed):
                        problems.append('%s:%d: includes "%s": %s may include only %s' %
                                        (rel, number, m.group(1), row,
                                         ", ".join(allowed) or "its own folder"))
                    m = re.match(r"\s*#\s*include\s*<([^>]+)>", line)
                    if m:
                        for bad in forbidden:
                            if m.group(1) == bad or (bad.endswith("/") and
                                                     m.group(1).startswith(bad)):
                                problems.append("%s:%d: includes <%s>, which %s may not" %
                                                (rel, number, m.group(1), row))
                if name.endswith((".cc", ".c", ".h")):
                    for fn, first, count in functions(text):
                        if count <= MAX_FUNCTION_LINES:
                            continue
                        short = fn.split("::")[-1]
                        key = next((k for k in long_functions
                                    if k[0] == rel and k[1].split("::")[-1] == short), None)
                        if key is None:
                            problems.append("%s:%d: function %s is %d lines (at most %d, or a "
                                            "row in docs/architecture.md's long-functions table)"
                                            % (rel, first, fn, count, MAX_FUNCTION_LINES))
                        elif count > long_functions[key]:
                            problems.append("%s:%d: function %s is %d lines, more than the %d "
                                            "docs/architecture.md allows it" %
                                            (rel, first, fn, count, long_functions[key]))
                        else:
                            seen_long.add(key)
    for key in sorted(set(long_functions) - seen_long):
        problems.append("docs/architecture.md: long-functions names %s in %s, which is not over "
                        "%d lines (or not there): remove the row" % (key[1], key[0],
                                                                     MAX_FUNCTION_LINES))
    for p in problems:
        print(p)
    if problems:
        print("check_structure: %d problem(s)" % len(problems))
        return 1
    print("check_structure: the includes follow docs/architecture.md's layers; no file over %d "
          "lines, no function over %d but the %d named" % (MAX_FILE_LINES, MAX_FUNCTION_LINES,
                                                          len(long_functions)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
