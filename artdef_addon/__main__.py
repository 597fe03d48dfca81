from .cli import main
from .headless import exit_process

# not sys.exit: the bpy 4.5 module can hang at exit (headless.exit_process)
exit_process(main())
