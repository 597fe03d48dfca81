import signal
import sys

from .cli import exit_process, main

# the package's import held Ctrl-C and SIGTERM to one line (artdef_addon/__init__.py); from here on
# the command's own handling applies
signal.signal(signal.SIGINT, signal.default_int_handler)
code = main()
if "bpy" in sys.modules:
    # Blender's teardown at interpreter exit must not be interrupted: a SIGINT there (Python has
    # restored the default handler by then) killed the process or crashed it inside bpy
    signal.signal(signal.SIGINT, signal.SIG_IGN)
# not sys.exit: the bpy 4.5 module can hang at exit (cli.exit_process)
exit_process(code)
