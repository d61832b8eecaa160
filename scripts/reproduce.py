"""The paper's experiments in simulation -> docs/results.md; see legged_casters/tools/reproduce.py."""

import sys

from legged_casters.tools.reproduce import main

if __name__ == "__main__":
    sys.exit(main())
