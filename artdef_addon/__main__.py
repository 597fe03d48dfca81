import signal
import sys

from .cli import exit_process, main

code = main()
if "bpy" in sys.modules:
    # Blender's teardown at interpreter exit must not be interrupted: a SIGINT there (Python has
    # restored the default handler by then) killed the process or crashed it inside bpy
    signal.signal(signal.SIGINT, signal.SIG_IGN)
# not sys.exit: the bpy 4.5 module can hang at exit (cli.exit_process)
exit_process(code)
