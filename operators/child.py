# SPDX-License-Identifier: GPL-3.0-or-later
"""The entry point of a worker process that has Blender: the extension's operators registered,
then the calls of :mod:`artdef_addon.procs` served until the parent goes.

    python operators/child.py -- -m artdef_addon.procs FOLDER             (the bpy module)
    blender -b --factory-startup --python-use-system-env --python operators/child.py -- -m ... FOLDER

:func:`.isolated.interpreter` builds that command line; :class:`artdef_addon.procs.Worker` adds the
part after ``--``. Run as a script, not imported: this file loads the extension it sits in under
the package name :data:`PACKAGE`, whatever the extension's folder or module name is (an installed
extension, a checkout), so a call's function is ``"artdef_child.operators.<module>:<name>"``. The
child starts on an empty file, so nothing of the user's startup file is read.
"""
import importlib.util
import os
import sys

#: the extension's package name in the child
PACKAGE = "artdef_child"
EXTENSION = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _load_extension():
    spec = importlib.util.spec_from_file_location(
        PACKAGE, os.path.join(EXTENSION, "__init__.py"), submodule_search_locations=[EXTENSION])
    package = importlib.util.module_from_spec(spec)
    sys.modules[PACKAGE] = package
    spec.loader.exec_module(package)
    return package


def main(argv) -> int:
    args = argv[argv.index("--") + 1:] if "--" in argv else argv[1:]
    folder = args[-1]
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    _load_extension().register()
    procs = importlib.import_module(PACKAGE + ".artdef_addon.procs")
    return procs.main([folder])


if __name__ == "__main__":
    code = main(sys.argv)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)          # no interpreter or Blender teardown: the parent has the result
