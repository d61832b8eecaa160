"""`scripts/gpu.py train`: one training on the lent GPU machine inside one device call.

A device call has a hard time limit and returns at most 8 files of at most 16 MiB each
(64 MiB in all), so this runs train.py with a deadline and packs its run folder to fit:

- train.py runs with the installed wheels on its path (PYTHONPATH=<site>:<repo>) and a
  kernel cache kept for a second call on a warm machine; its output goes to the console
  and to OUT/train.log;
- at `deadline_s` after the start (minus the time packing needs) it gets SIGTERM, which
  train.py turns into a clean stop naming its newest checkpoint. (Its --max_minutes
  counts from the first iteration, after the env is built: on Warp with an empty kernel
  cache that is 80-100 s of compiling, which the deadline covers and --max_minutes does
  not);
- the run folder (train.py prints it) goes into one tar archive, newest checkpoints
  first when it does not fit in full, cut into OUT/<run>.tar.00, .01, ...: here
  `cat <files_at>/<run>.tar.* | tar xf - -C logs/<experiment>` puts it back.
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

from legged_casters.tools.gpu_wheels import MIB

REPO = Path(__file__).resolve().parents[2]
PART_BYTES = 15 * MIB
"""Bytes per returned part: under the device tool's 16 MiB per file."""
MAX_PARTS = 4
"""Parts of the archive: with train.log 5 of the 8 returned files, at most 60 MiB of the 64."""
PACK_MARGIN_S = 20.0
"""Seconds kept after the training for its clean stop and the packing."""
RUN_FOLDER = re.compile(r"^\[train\.py\] run folder (.+)$")
CHECKPOINT = re.compile(r"^model_(\d+)\.pt$")


def pack_run(run_dir: Path, out: Path, part_bytes: int = PART_BYTES, max_parts: int = MAX_PARTS) -> dict:
    """Archive `run_dir` (as a folder named like it) into out/<name>.tar.NN parts of at most
    `part_bytes`, at most `max_parts` of them. Every file but the numbered checkpoints goes in;
    then model_best.pt and the checkpoints newest first while the archive still fits. Returns
    the part paths, the files packed and the checkpoints left out."""
    run_dir = Path(run_dir)
    cap = part_bytes * max_parts
    files = sorted(p for p in run_dir.iterdir() if p.is_file())
    numbered = sorted((p for p in files if CHECKPOINT.match(p.name)), key=lambda p: -int(CHECKPOINT.match(p.name)[1]))
    others = [p for p in files if p not in numbered]
    # a tar header and padding cost at most 1 KiB per file, plus the end blocks
    size = lambda paths: sum(p.stat().st_size + 1024 for p in paths) + 10 * 1024  # noqa: E731
    chosen = list(others)
    if size(chosen) > cap:
        raise ValueError(
            f"{run_dir} holds {size(chosen) / MIB:.1f} MiB besides its checkpoints, more than the "
            f"{cap / MIB:.0f} MiB that come back"
        )
    left_out = []
    for p in numbered:
        if size([*chosen, p]) <= cap:
            chosen.append(p)
        else:
            left_out.append(p.name)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for p in sorted(chosen):
            tar.add(p, arcname=f"{run_dir.name}/{p.name}")
    data = buf.getvalue()
    out.mkdir(parents=True, exist_ok=True)
    parts = []
    for i in range(0, len(data), part_bytes):
        part = out / f"{run_dir.name}.tar.{i // part_bytes:02d}"
        part.write_bytes(data[i : i + part_bytes])
        parts.append(part)
    return {"parts": parts, "packed": sorted(p.name for p in chosen), "left_out": sorted(left_out)}


def run_training(
    train_args: list[str],
    out: Path,
    deadline_s: float,
    site: Path | None,
    warp_cache: Path | None,
    started: float | None = None,
) -> int:
    """train.py with `train_args` until it ends or the deadline; then pack its run folder
    into `out`. Returns train.py's exit status (or 1 if it never named its run folder)."""
    started = time.time() if started is None else started
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(
        [*([str(site)] if site else []), str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    if warp_cache is not None:
        env.setdefault("WARP_CACHE_PATH", str(warp_cache))
    cmd = [sys.executable, str(REPO / "train.py"), *train_args]
    print(f"[gpu_train] {' '.join(cmd)}", flush=True)
    run_dir: list[Path] = []
    log_path = out / "train.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

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
        stop_at = started + deadline_s - PACK_MARGIN_S
        try:
            rc = proc.wait(timeout=max(stop_at - time.time(), 1.0))
        except subprocess.TimeoutExpired:
            print(f"[gpu_train] deadline: {deadline_s:g} s since the start; stopping train.py (SIGTERM)", flush=True)
            proc.send_signal(signal.SIGTERM)
            try:
                rc = proc.wait(timeout=PACK_MARGIN_S / 2)
            except subprocess.TimeoutExpired:
                proc.kill()
                rc = proc.wait()
        reader.join(timeout=5)
    print(f"[gpu_train] train.py exit status {rc} after {time.time() - started:.0f} s", flush=True)
    if not run_dir:
        print(f"[gpu_train] train.py named no run folder: nothing to pack (its output: {log_path})", flush=True)
        return rc or 1
    packed = pack_run(run_dir[0], out)
    names = ", ".join(p.name for p in packed["parts"])
    print(f"[gpu_train] packed {len(packed['packed'])} files of {run_dir[0]} into {names}", flush=True)
    if packed["left_out"]:
        print(f"[gpu_train] left out (no room): {', '.join(packed['left_out'])}", flush=True)
    experiment = run_dir[0].parent.name
    print(
        f"[gpu_train] here: cat <files_at>/{run_dir[0].name}.tar.* | tar xf - -C logs/{experiment}",
        flush=True,
    )
    return rc
