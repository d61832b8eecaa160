"""torch.distributed.run as `train.py --procs N` starts it, quiet when stopped.

A Ctrl-C in a terminal reaches every process of the job: the workers stop with their newest
checkpoint and the command that continues from it, and torchrun's agent raises
SignalException, which would end the job with a Python traceback and two logging warnings
under those lines. Here the agent still shuts its workers down as it always does; its
SignalException ends the launcher with the shell's code for that signal (130 for SIGINT,
143 for SIGTERM) and nothing more. Any other failure (a worker that crashed) is reported by
torchrun as before.

    python -m legged_casters.tools.launcher --standalone --nnodes=1 --nproc_per_node=2 -m MODULE ARGS
"""

from __future__ import annotations

import logging
import os
import sys


def main() -> int:
    # The agent's warnings ("Received 2 death signal, shutting down workers", "Sending
    # process N closing signal SIGINT") say what a stop does anyway; errors still show.
    # Its loggers read LOGLEVEL when imported, the process handler's inherits this one's.
    os.environ.setdefault("LOGLEVEL", "ERROR")
    logging.getLogger("torch.distributed.elastic").setLevel(os.environ["LOGLEVEL"])
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.run import main as torchrun

    try:
        torchrun()
    except SignalException as stop:
        return 128 + int(stop.sigval)
    return 0


if __name__ == "__main__":
    sys.exit(main())
