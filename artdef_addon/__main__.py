import sys

from .cli import main

code = main()
if "bpy" in sys.modules:
    # The bpy 4.5 module can deadlock in its C++ static destructors at process
    # exit after a glTF import/export (measured: the outputs are written in 30 s,
    # then the process waits on a futex forever).  Run the Python exit handlers
    # (temporary extension repository clean-up), flush, and leave without the
    # C-level teardown.  Blender version difference: see operators/compat.py.
    import atexit
    import os

    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 0)
sys.exit(code)
