"""What every Python test in tests/tools starts with, shared from here rather than copied (as the
C++ tests share tests/<layer>/*_test_util.h): the checkout's paths, tools/ on sys.path (so a test
imports motionio, figures, ... directly), the motionctl binary ctest hands over, and exit 77 -- which
ctest reports as "skipped", not "failed" -- when the interpreter lacks a module or the binary is
missing. Imported first, before the modules it checks for."""

import importlib
import os
import sys

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TOOLS = os.path.join(REPO, "tools")
BINARY = os.environ.get("MOTIONCTL_BINARY") or os.path.join(REPO, "build", "motionctl")
if TOOLS not in sys.path:
    sys.path.insert(0, TOOLS)


def skip(reason):
    """Ends the test run as skipped (exit 77), saying why."""
    print(f"skipping: {reason}")
    sys.exit(77)


def require_modules(*names):
    """Skips unless every module imports (e.g. "numpy", "h5py", "PIL.Image"): the wrong interpreter
    is a reason to skip, not a failure (run with /usr/bin/python3, Debian's, which has them all)."""
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError as e:
            skip(f"{e} (run with /usr/bin/python3)")


def require_binary():
    """Skips unless the motionctl binary (MOTIONCTL_BINARY, else build/motionctl) is there."""
    if not os.access(BINARY, os.X_OK):
        skip(f"no motionctl binary at {BINARY} (set MOTIONCTL_BINARY)")
