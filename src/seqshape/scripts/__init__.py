"""One module per ``seqshape`` sub-command: ``HELP``, ``add_arguments(parser)``, ``run(args)``."""
