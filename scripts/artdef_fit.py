# SPDX-License-Identifier: GPL-3.0-or-later
"""Run the artdef command line inside Blender, or with the bpy module.

    blender -b -P scripts/artdef_fit.py -- fit SCAN.npz --links 3 --glb out.glb
    python scripts/artdef_fit.py -- fit SCAN.npz --links 3 --glb out.glb

This is the Blender side's entry point of the command line: everything after ``--``
goes to ``artdef_addon.cli.main`` (same arguments as ``python -m artdef_addon``)
together with the Blender layer, ``operators/headless.py`` (:func:`blender_layer`),
which builds the .blend, .glb, .fbx and .png outputs and reads animated inputs.
``python -m artdef_addon`` hands a command that needs Blender to this script. The
repository root is put on ``sys.path`` so the checkout's ``artdef_addon`` is used;
the operators come from the enabled extension if there is one, else from this
checkout (see operators/headless.py).
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


def blender_layer():
    """The Blender layer's headless module: ``<extension>.operators.headless`` when the core runs
    inside the installed extension package, else ``operators/headless.py`` of this checkout (a
    module that works loaded on its own from its file)."""
    import importlib
    import importlib.util
    import artdef_addon
    parent = artdef_addon.__name__.rpartition(".")[0]
    if parent:
        return importlib.import_module(parent + ".operators.headless")
    name = "artdef_headless_entry"
    if name in sys.modules:
        return sys.modules[name]
    path = os.path.join(ROOT, "operators", "headless.py")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def run(argv=None):
    import signal

    def interrupted_while_loading(signum, frame):
        # as ``python -m artdef_addon`` (artdef_addon/__init__.py): one line, nothing written yet
        what = "terminated" if signum == signal.SIGTERM else "interrupted"
        sys.stderr.write(f"artdef: error: {what}; no file was written or changed\n")
        sys.stderr.flush()
        os._exit(128 + signum)

    old = {}
    if "bpy" not in sys.modules:        # plain Python (inside Blender, Blender keeps its own handlers)
        try:
            old = {s: signal.signal(s, interrupted_while_loading) for s in (signal.SIGINT, signal.SIGTERM)}
        except ValueError:      # not the main thread
            old = {}
    from artdef_addon.cli import main
    for s, handler in old.items():
        signal.signal(s, handler)

    code = main(_args(sys.argv if argv is None else argv), blender=blender_layer())
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
