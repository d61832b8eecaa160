#!/usr/bin/env python3
"""The GPU check, prepared here and run there in one command (research/gpu.md).

    python dev/gpu_loan/gpu.py prepare                # here: download the wheels the GPU machine lacks
                                                      # into .whl/, pack them into device calls, print them
    python dev/gpu_loan/gpu.py prepare --dry-run      # only say which packages (no network)
    python3 dev/gpu_loan/gpu.py stash                 # there, in every call but the last: keep the wheels
    python3 dev/gpu_loan/gpu.py run --out $OUT        # there, in the last call: install, then every stage
    python dev/gpu_loan/gpu.py run --cpu --out DIR    # anywhere: the same stages, Warp on the CPU, tiny sizes
    python dev/gpu_loan/gpu.py report gpu_check.json  # the table again, from a run's JSON
    python3 dev/gpu_loan/gpu.py train --out $OUT --deadline-s 560 -- --task caster_omni --sim_backend warp ...
                                                      # there, instead of `run`: install, then one training
                                                      # with a deadline, its run folder packed (gpu_train.py)

`run` writes DIR/gpu_check.json (everything measured), DIR/gpu_check.txt (a table) and
DIR/gpu_check.log (the stages' output, cut to their tails). The stages and their time
limits are described in dev/gpu_loan/gpu_check.py.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFAULT_WORK = Path(tempfile.gettempdir()) / "legged_casters_gpu_check"
"""The check's runs, logs and Warp kernel cache (work/warp_cache, which `train` uses too)."""

import gpu_check  # noqa: E402  (the modules beside this script; standard library only)
import gpu_train  # noqa: E402
import gpu_wheels  # noqa: E402


def cmd_prepare(args) -> int:
    have = gpu_wheels.read_have(Path(args.have)) if args.have else None
    manifest = gpu_wheels.prepare(REPO, dry_run=args.dry_run, have=have)
    if args.dry_run:
        return 0
    print()
    print(gpu_wheels.describe(manifest))
    calls = gpu_wheels.device_calls(manifest)
    print(f"\nOn the GPU machine: {len(calls)} device `run` calls, back to back (a machine idle for ~30 s is")
    print("given back and a fresh one has none of the earlier calls' wheels):")
    for i, call in enumerate(calls, 1):
        timeout = f", timeout_s {args.timeout_s}" if i == len(calls) else ", timeout_s 120"
        print(f"  {i}. carry {call['carry']}{timeout}\n     command: {call['command']}")
    print(f"\nmanifest: {REPO / gpu_wheels.WHEEL_DIR / gpu_wheels.MANIFEST}")
    return 0


def cmd_stash(args) -> int:
    st = gpu_wheels.stash(REPO, Path(args.stash))
    return 0 if st["present"] else 1


def install(stash: Path, site: Path) -> dict:
    """Stash this call's wheels, install every complete one into `site`, list unmet requirements."""
    t0 = time.time()
    try:
        result = gpu_wheels.install(REPO, stash, site)
        result["requirements"] = gpu_wheels.check_requirements(site, result["left_behind"])
    except Exception as err:  # the caller decides whether to go on
        result = {"status": "error", "error": f"{type(err).__name__}: {err}", "problems": [], "requirements": []}
    result.setdefault("seconds", round(time.time() - t0, 1))
    return result


def _print_install(result: dict) -> None:
    for line in result["problems"] + result["requirements"] + ([result["error"]] if "error" in result else []):
        print(f"[install] {line}")


def cmd_install(args) -> int:
    result = install(Path(args.stash), Path(args.site))
    _print_install(result)
    return 0 if result["status"] == "ok" else 1


def cmd_run(args) -> int:
    out = Path(args.out).resolve()
    work = Path(args.work).resolve() if args.work else DEFAULT_WORK
    install_result, site = None, None
    t0 = time.time()
    if not args.cpu and not args.no_install:
        site = Path(args.site)
        install_result = install(Path(args.stash), site)  # on an error go on: the stages say what is missing
        print(f"[gpu_check] install: {install_result['status']}", flush=True)
    stages = args.stages.split(",") if args.stages else None
    budget = args.budget_s - (time.time() - t0)
    limits = {}
    for item in args.limit:
        stage, _, seconds = item.partition("=")
        limits[stage] = float(seconds)
    results = gpu_check.run_check(
        out,
        cpu=args.cpu,
        budget_s=budget,
        work=work,
        install_result=install_result,
        site=site,
        stages=stages,
        limits=limits,
    )
    print()
    print(gpu_check.summary_table(results))
    print(f"\n[gpu_check] wrote {out / 'gpu_check.json'}, {out / 'gpu_check.txt'}, {out / 'gpu_check.log'}")
    return 0


def cmd_train(args) -> int:
    t0 = time.time()
    train_args = args.train_args[1:] if args.train_args[:1] == ["--"] else args.train_args
    if not train_args:
        print("gpu.py train: give train.py's arguments after --, e.g. -- --task caster_omni --sim_backend warp")
        return 2
    if args.deadline_s < gpu_train.MIN_DEADLINE_S:
        print(f"gpu.py train: --deadline-s {args.deadline_s:g} is too short: at least {gpu_train.MIN_DEADLINE_S:g}")
        return 2
    site = None
    if not args.no_install:
        site = Path(args.site)
        result = install(Path(args.stash), site)
        _print_install(result)
        if result["status"] != "ok":
            print(f"[gpu_train] the install failed ({result['status']}): not training")
            return 1
    cache = Path(args.warp_cache) if args.warp_cache else DEFAULT_WORK / "warp_cache"
    return gpu_train.run_training(train_args, Path(args.out), args.deadline_s, site, cache, started=t0)


def cmd_report(args) -> int:
    import json

    print(gpu_check.summary_table(json.loads(Path(args.json).read_text())))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    pre = sub.add_parser("prepare", help="here: download and pack the wheels, print the device calls")
    pre.add_argument("--dry-run", action="store_true", help="only list the packages to carry (no network)")
    pre.add_argument("--have", help="a file of the GPU machine's packages (pip list/freeze), instead of KINDS.md's")
    pre.add_argument("--timeout-s", type=int, default=500, help="timeout_s printed for the last call")
    for name, text in (("stash", "there: keep this call's wheels"), ("install", "there: join and install")):
        s = sub.add_parser(name, help=text)
        s.add_argument("--stash", default=gpu_wheels.DEFAULT_STASH)
        if name == "install":
            s.add_argument("--site", default=gpu_wheels.DEFAULT_SITE)
    run = sub.add_parser("run", help="there (or --cpu anywhere): install, then the stages")
    run.add_argument("--out", required=True, help="folder for gpu_check.json / .txt / .log")
    run.add_argument("--cpu", action="store_true", help="Warp on the CPU device, tiny sizes (CI)")
    run.add_argument("--budget-s", type=float, default=None, help="wall budget (default: 420 s; --cpu 300 s)")
    run.add_argument("--work", help=f"runs, logs, kernel cache (default: {DEFAULT_WORK})")
    run.add_argument("--stages", help=f"a subset, comma-separated, of: {','.join(gpu_check.STAGES)}")
    run.add_argument(
        "--limit", action="append", default=[], metavar="STAGE=S", help="a stage's time limit in seconds (repeatable)"
    )
    run.add_argument("--stash", default=gpu_wheels.DEFAULT_STASH)
    run.add_argument("--site", default=gpu_wheels.DEFAULT_SITE)
    run.add_argument("--no-install", action="store_true", help="use this interpreter's packages as they are")
    tr = sub.add_parser("train", help="there: install, then one train.py run with a deadline, its run folder packed")
    tr.add_argument("--out", required=True, help="folder for train.log and the run folder's <run>.tar.NN parts")
    tr.add_argument(
        "--deadline-s",
        type=float,
        default=560.0,
        help="seconds from this command's start until the run is packed: train.py gets SIGTERM 20 s before it "
        "(default 560: a device call's 600 s timeout minus the transfers; at least 60)",
    )
    tr.add_argument("--no-install", action="store_true", help="use this interpreter's packages as they are")
    tr.add_argument("--stash", default=gpu_wheels.DEFAULT_STASH)
    tr.add_argument("--site", default=gpu_wheels.DEFAULT_SITE)
    tr.add_argument("--warp-cache", help=f"Warp's kernel cache (default: {DEFAULT_WORK / 'warp_cache'}, the check's)")
    tr.add_argument("train_args", nargs=argparse.REMAINDER, help="-- then train.py's arguments")
    rep = sub.add_parser("report", help="print the table of a run's gpu_check.json")
    rep.add_argument("json")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "run" and args.budget_s is None:
        args.budget_s = 300.0 if args.cpu else 420.0
    commands = {
        "prepare": cmd_prepare,
        "stash": cmd_stash,
        "install": cmd_install,
        "run": cmd_run,
        "report": cmd_report,
        "train": cmd_train,
    }
    return commands[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
