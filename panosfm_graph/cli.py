"""The `panosfm` command line: thin layers over public Python functions."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    print("panosfm: under construction", file=sys.stderr)
    return 0
