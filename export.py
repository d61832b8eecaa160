#!/usr/bin/env python3
"""Export a trained policy: `python export.py --help`. The logic is in legged_casters/tools/export.py."""

import sys
from pathlib import Path

from legged_casters.tools.export import main

if __name__ == "__main__":
    sys.exit(main(default_log_root=Path(__file__).resolve().parent / "logs"))
