"""Evaluate a caster policy through fixed scenarios; see legged_casters/tools/evaluate.py."""

import sys

from legged_casters.tools.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
