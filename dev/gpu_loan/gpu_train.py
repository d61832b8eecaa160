"""`dev/gpu_loan/gpu.py train`: one training on the lent GPU machine inside one device call.

A device call has a hard time limit and returns at most 8 files of at most 16 MiB each
(64 MiB in all), so this runs train.py with a deadline and packs its run folder to fit:

- train.py runs with the installed wheels on its path (PYTHONPATH=<site>:<repo>) and a
  kernel cache kept for a second call on a warm machine; its output goes to the console
  and to OUT/train.log;
- at `deadline_s` after the start less PACK_MARGIN_S it gets SIGTERM, which train.py turns
  into a clean stop at its newest checkpoint (exit status 130, reported as 0 here); its
  process group is killed if it has not ended 10 s later. (Its --max_minutes
  counts from the first iteration, after the env is built: on Warp with an empty kernel
  cache that took 79 s on the H200, which the deadline covers and --max_minutes does
  not);
- the run folder (train.py prints it) goes into one tar archive, newest checkpoints
  first when it does not fit in full, cut into OUT/<run>.tar.00, .01, ...: here
  `mkdir -p logs/<experiment> && cat <files_at>/<run>.tar.* | tar xf - -C logs/<experiment>`
  puts it back.
"""

from __future__ import annotations

import io
import os
import re
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

import gpu_check
from gpu_wheels import MIB

REPO = gpu_check.REPO
PART_BYTES = 15 * MIB
"""Bytes per returned part: under the device tool's 16 MiB per file."""
MAX_PARTS = 4
"""Parts of the archive: with train.log 5 of the 8 returned files, at most 60 MiB of the 64."""
PACK_MARGIN_S = 20.0
"""Seconds kept after the training for its clean stop and the packing."""
MIN_DEADLINE_S = 60.0
"""Shortest --deadline-s (gpu.py checks it before installing): the packing margin plus time
for train.py to start at all."""
RUN_FOLDER = re.compile(r"^\[train\.py\] run folder (.+)$")
SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]")
CHECKPOINT = re.compile(r"^model_(\d+)\.pt$")


def pack_run(run_dir: Path, out: Path, part_bytes: int = PART_BYTES, max_parts: int = MAX_PARTS) -> dict:
    """Archive `run_dir` (as a folder named like it) into out/<name>.tar.NN parts of at most
    `part_bytes`, at most `max_parts` of them. Every file goes in; while the archive is too
    large the oldest numbered checkpoint (model_<it>.pt) is left out. Returns the part
    paths, the files packed and the checkpoints left out; ValueError if even without any
    numbered checkpoint it does not fit."""
    run_dir = Path(run_dir)
    prefix = SAFE_NAME.sub("_", run_dir.name)  # the device tool returns only such names
    cap = part_bytes * max_parts
    files = sorted(p for p in run_dir.iterdir() if p.is_file())
    oldest_first = sorted(
        (p for p in files if CHECKPOINT.match(p.name)), key=lambda p: int(CHECKPOINT.match(p.name)[1])
    )
    chosen, left_out = list(files), []
    while True:
        data = _tar(run_dir.name, chosen)
        if len(data) <= cap:
            break
        if not oldest_first:
            raise ValueError(
                f"{run_dir} holds {len(data) / MIB:.1f} MiB without its numbered checkpoints, more than the "
                f"{cap / MIB:.1f} MiB ({max_parts} parts of {part_bytes / MIB:.1f} MiB) that come back"
            )
        dropped = oldest_first.pop(0)
        chosen.remove(dropped)
        left_out.append(dropped.name)
    out.mkdir(parents=True, exist_ok=True)
    parts = []
    for i in range(0, len(data), part_bytes):
        part = out / f"{prefix}.tar.{i // part_bytes:02d}"
        part.write_bytes(data[i : i + part_bytes])
        parts.append(part)
    return {"parts": parts, "packed": sorted(p.name for p in chosen), "left_out": sorted(left_out)}


def _tar(folder: str, paths: list[Path]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for p in sorted(paths):
            tar.add(p, arcname=f"{folder}/{p.name}")
    return buf.getvalue()


def run_training(
    train_args: list[str], out: Path, deadline_s: float, site: Path | None, warp_cache: Path, started: float
) -> int:
    """train.py with `train_args` until it ends or the deadline (seconds after `started`, at
    least MIN_DEADLINE_S);
    then pack its run folder into `out`. Returns 0 when train.py ended by itself with 0 or
    stopped cleanly at the deadline, else its status (128 + signal when a signal ended it;
    1 when nothing could be packed)."""
    out.mkdir(parents=True, exist_ok=True)
    env = dict(gpu_check.child_env(site), WARP_CACHE_PATH=str(warp_cache))
    cmd = [sys.executable, str(REPO / "train.py"), *train_args]
    print(f"[gpu_train] {' '.join(cmd)}", flush=True)
    run_dir: list[Path] = []
    log_path = out / "train.log"
    stopped = False
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace",
            start_new_session=True,  # its own process group: a kill reaches whatever it started
        )  # fmt: skip

        def relay() -> None:
            for line in proc.stdout:
                log.write(line)
                log.flush()
                sys.stdout.write(line)
                sys.stdout.flush()
                m = RUN_FOLDER.match(line.rstrip("\n"))
                if m:
                    run_dir.append(Path(m[1]))

        reader = threading.Thread(target=relay, daemon=True)
        reader.start()
        try:
            rc = proc.wait(timeout=max(started + deadline_s - PACK_MARGIN_S - time.time(), 1.0))
        except subprocess.TimeoutExpired:
            stopped = True
            print(
                f"[gpu_train] deadline: {time.time() - started:.0f} s since the start ({deadline_s:g} s less "
                f"{PACK_MARGIN_S:g} s to pack); stopping train.py (SIGTERM)",
                flush=True,
            )
            proc.send_signal(signal.SIGTERM)
            try:
                rc = proc.wait(timeout=PACK_MARGIN_S / 2)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                rc = proc.wait()
        reader.join(timeout=5)
    status = 128 - rc if rc < 0 else rc  # a signal's exit status as a shell reports it
    print(f"[gpu_train] train.py exit status {status} after {time.time() - started:.0f} s", flush=True)
    if stopped and rc == 130:
        print("[gpu_train] train.py stopped cleanly at the deadline (its newest checkpoint is the run's last)")
        status = 0
    elif stopped:
        print("[gpu_train] train.py had not reached its training loop (still building the env?) when stopped")
    if not run_dir:
        print(f"[gpu_train] train.py named no run folder: nothing to pack (its output: {log_path})", flush=True)
        return status or 1
    try:
        packed = pack_run(run_dir[0], out)
    except ValueError as err:
        print(f"[gpu_train] cannot pack the run: {err}", flush=True)
        return 1
    names = ", ".join(p.name for p in packed["parts"])
    print(f"[gpu_train] packed {len(packed['packed'])} files of {run_dir[0]} into {names}", flush=True)
    if packed["left_out"]:
        print(f"[gpu_train] left out (no room): {', '.join(packed['left_out'])}", flush=True)
    experiment = run_dir[0].parent.name
    prefix = packed["parts"][0].name.rsplit(".tar.", 1)[0]
    unpack = f"cat <files_at>/{prefix}.tar.* | tar xf - -C logs/{experiment}"
    print(f"[gpu_train] here: mkdir -p logs/{experiment} && {unpack}", flush=True)
    return status
