"""``python3 -m hil.study SPEC.toml ...``: the same as ``hil study``."""

import sys

from hil.study.command import main

if __name__ == "__main__":
    sys.exit(main())
