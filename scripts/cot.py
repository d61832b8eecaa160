"""The paper's Table II (cost of transport of three robots); see legged_casters/tools/cot.py."""

import sys

from legged_casters.tools.cot import main

if __name__ == "__main__":
    sys.exit(main())
