#!/usr/bin/env python3
"""Train a policy: `python train.py --help`. The logic is in legged_casters/tools/train.py."""

import sys
from pathlib import Path

from legged_casters.tools.train import main

if __name__ == "__main__":
    sys.exit(main(default_log_root=Path(__file__).resolve().parent / "logs"))
