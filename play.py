#!/usr/bin/env python3
"""Play a policy: `python play.py --help`. The logic is in legged_casters/tools/play.py."""

import sys
from pathlib import Path

from legged_casters.tools.play import main

if __name__ == "__main__":
    sys.exit(main(default_log_root=Path(__file__).resolve().parent / "logs"))
