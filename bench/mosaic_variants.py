"""CLI entry points of bench/mosaic.py's variants: ``orthowarp``'s own ``main`` with one step of
the mosaic changed in that child process only, for measuring what the step is worth (the
library has no switch for it).

- ``no_build_ahead``: the tile processes do not build their first images while the plan is
  made (``pipeline.mosaic._ahead_on`` returns a hook that does nothing); they still start
  beside the plan, and build their images when their tiles come.
"""

import importlib


def no_build_ahead():
    """``orthowarp`` (its arguments from ``sys.argv``) without the build-ahead."""
    module = importlib.import_module("orthowarp.pipeline.mosaic")
    module._ahead_on = lambda procs, tile_size, on: (lambda plan: None)
    from orthowarp.cli import main

    return main()
