"""Command line: ``python -m prtt_addon <command> ...`` (see ``--help``)."""
import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
