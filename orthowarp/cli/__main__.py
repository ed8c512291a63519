"""``python -m orthowarp.cli``: the ``orthowarp`` command, every command included."""

from . import main

if __name__ == "__main__":  # pragma: no cover
    main()
