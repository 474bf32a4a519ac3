"""One-way layers (tools/check_layers.py): this checkout has no upward include, and the
check does catch one: a lower layer including a higher layer's header (by its
src-relative or a relative path), a folder under src/ on no layer. Same-layer and
downward includes, system headers and src/pch/ pass."""

import os
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import REPO, TOOLS

CHECK = os.path.join(TOOLS, "check_layers.py")
import check_layers  # noqa: E402


def run_check(root):
    return subprocess.run([sys.executable, CHECK, "--root", root], capture_output=True, text=True, timeout=120)


def write(root, rel, text):
    path = os.path.join(root, rel)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write(text)


class LayerCheckTest(unittest.TestCase):
    def test_this_checkout_is_one_way(self):
        r = run_check(REPO)
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)

    def test_every_layer_folder_exists(self):
        for layer in check_layers.LAYERS:
            self.assertTrue(os.path.isdir(os.path.join(REPO, check_layers.FOLDERS[layer])), layer)

    def tree(self):
        d = tempfile.mkdtemp(prefix="mc_layers_")
        self.addCleanup(lambda: subprocess.run(["rm", "-rf", d]))
        write(d, "src/core/config.h", "#pragma once\n#include <string>\n")
        write(d, "src/models/net.h", '#pragma once\n#include "core/config.h"\n')
        write(d, "src/samplers/sampler.h", '#pragma once\n#include "models/net.h"\n')
        write(d, "src/pch/torch_pch.h", "#include <torch/torch.h>\n")
        write(d, "eval/metrics.h", '#pragma once\n#include "samplers/sampler.h"\n')
        return d

    def test_downward_and_same_layer_includes_pass(self):
        d = self.tree()
        write(d, "src/models/prior.cpp", '#include "models/net.h"\n#include "net.h"\n#include <vector>\n')
        r = run_check(d)
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)

    def test_upward_include_fails_naming_file_line_and_layers(self):
        d = self.tree()
        write(d, "src/models/prior.cpp", '// a model\n#include "models/net.h"\n#include "samplers/sampler.h"\n')
        r = run_check(d)
        self.assertEqual(r.returncode, 1)
        self.assertIn('src/models/prior.cpp:3: models includes "samplers/sampler.h" of the higher layer samplers',
                      r.stdout)

    def test_relative_upward_include_fails(self):
        d = self.tree()
        write(d, "src/control/anchors.cpp", '#include "../../eval/metrics.h"\n')
        r = run_check(d)
        self.assertEqual(r.returncode, 1)
        self.assertIn("src/control/anchors.cpp:1: control includes", r.stdout)
        self.assertIn("of the higher layer eval", r.stdout)

    def test_folder_on_no_layer_fails(self):
        d = self.tree()
        write(d, "src/protocolz/p.cpp", '#include "core/config.h"\n')
        r = run_check(d)
        self.assertEqual(r.returncode, 1)
        self.assertIn("src/protocolz/ is on no layer", r.stdout)

    def test_bad_root_is_exit_2(self):
        with tempfile.TemporaryDirectory() as d:
            r = run_check(d)
        self.assertEqual(r.returncode, 2)
        self.assertIn("has no src/ folder", r.stderr)


if __name__ == "__main__":
    unittest.main()
