# SPDX-License-Identifier: GPL-3.0-or-later
"""Run the artdef command line inside Blender, or with the bpy module.

    blender -b -P scripts/artdef_fit.py -- fit SCAN.npz --links 3 --glb out.glb
    python scripts/artdef_fit.py -- fit SCAN.npz --links 3 --glb out.glb

Everything after ``--`` goes to ``artdef_addon.cli.main`` (same arguments as
``python -m artdef_addon``).  The repository root is put on ``sys.path`` so the
checkout's ``artdef_addon`` is used; the operators come from the enabled
extension if there is one, else from this checkout (see operators/headless.py).
"""
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def _args(argv):
    # Blender passes its own arguments too: ours follow the first "--".
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return argv[1:]


def run(argv=None):
    from artdef_addon.cli import main

    code = main(_args(sys.argv if argv is None else argv))
    return 0 if code is None else int(code)


if __name__ == "__main__":
    code = run()
    if "bpy" in sys.modules:   # no SIGINT inside Blender's teardown (see artdef_addon/__main__.py)
        import signal
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if not getattr(sys.modules["bpy"].app, "binary_path", ""):
            # the bpy module (not inside Blender): it can hang at exit on 4.5
            from artdef_addon.cli import exit_process
            exit_process(code)
    sys.exit(code)
