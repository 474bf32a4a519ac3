"""Every Catch2 TEST_CASE name can become one ctest entry: catch_discover_tests hands the
names to CMake as a list, so a ';' in a name splits it into entries that match no test
(they fail under --warn NoTests with no hint why), and an unbalanced '[' (as in
"[start, end)") makes CMake keep every later ';' inside the bracket, merging all the
following tests into one entry that matches none. This check names the file and line."""

import os
import re
import sys
import unittest

from tools_test_util import REPO
# The name is the first string literal after TEST_CASE( (possibly on the next line);
# adjacent literals are joined as the compiler joins them.
TEST_CASE = re.compile(r'TEST_CASE\s*\(\s*((?:"(?:[^"\\]|\\.)*"\s*)+)', re.S)


def brackets_balanced(name):
    depth = 0
    for c in name:
        depth += {"[": 1, "]": -1}.get(c, 0)
        if depth < 0:
            return False
    return depth == 0


def bad_names(root):
    out = []
    for d, _, files in os.walk(os.path.join(root, "tests")):
        for f in files:
            if not f.endswith(".cpp"):
                continue
            path = os.path.join(d, f)
            text = open(path, encoding="utf-8").read()
            for m in TEST_CASE.finditer(text):
                name = "".join(re.findall(r'"((?:[^"\\]|\\.)*)"', m.group(1)))
                if ";" in name or not brackets_balanced(name):
                    line = text.count("\n", 0, m.start()) + 1
                    out.append(f"{os.path.relpath(path, root)}:{line}: {name!r}")
    return out


class TestNames(unittest.TestCase):
    def test_finds_a_semicolon(self):
        # The pattern itself: a name split over two literals, with a ';' in the second.
        sample = 'TEST_CASE(\n  "a, b "\n  "c; d", "[x]") {'
        m = TEST_CASE.search(sample)
        self.assertIsNotNone(m)
        self.assertIn(";", "".join(re.findall(r'"((?:[^"\\]|\\.)*)"', m.group(1))))

    def test_brackets(self):
        self.assertTrue(brackets_balanced("token-aligned [B, L, width]"))
        self.assertFalse(brackets_balanced("inside [start, end), the default"))
        self.assertFalse(brackets_balanced("a ] b ["))

    def test_no_name_has_a_semicolon(self):
        bad = bad_names(REPO)
        self.assertEqual(bad, [], "TEST_CASE names with ';' or an unbalanced '[' (CMake splits or merges them into "
                         "ctest entries that run nothing; use ',' and balanced brackets):\n" + "\n".join(bad))


if __name__ == "__main__":
    unittest.main()
