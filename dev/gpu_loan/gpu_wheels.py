"""Wheels for the GPU machine, which reaches no package registry: which ones, their
download here, their split into transfers, and their join and install there.

Standard library only (plus `packaging`, present on both machines, for requirement
markers): the GPU side runs this before anything of ours is installed.

The device tool moves at most 64 MiB per call, the working tree included; warp-lang's
wheel alone is ~149 MB. `plan_transfers` packs the wheels into per-call folders
`.whl/call<k>/` (a wheel larger than a call's room is cut into parts across calls),
each with a copy of the manifest (names, sizes, sha256 of every wheel and part).
On the GPU machine `stash` copies each carried folder into a folder outside the
checkout (it survives between calls while the machine stays up), `join` rebuilds
and checks every wheel, `install` puts them into a `--target` folder with pip.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path

MIB = 1 << 20
TRANSFER_LIMIT = 64 * MIB
"""What one device call moves: the working tree plus the carried paths."""
PART_MAX = 60 * MIB
MARGIN = 2 * MIB
"""Room kept free in every call (files added to the checkout after `prepare`, rounding)."""

WHEEL_DIR = ".whl"
MANIFEST = "manifest.json"
DEFAULT_STASH = "/tmp/legged_casters_wheels"
DEFAULT_SITE = "/tmp/site"

ROOTS = ("mujoco", "mujoco-warp", "warp-lang", "rsl-rl-lib", "tensordict", "eclipse-zenoh")
"""The project's dependencies the GPU machine lacks; their own needs are found from their metadata."""
NOT_CARRIED = {
    "imageio-ffmpeg": "only play.py's video writer uses it (an ffmpeg binary, ~30 MB)",
    "cma": "only scripts/top_speed.py's CMA-ES uses it",
    "cryptography": "only the deploy certificates (legged_casters.deploy.certs) use it",
}
"""Project dependencies missing there that the GPU check does not need (never downloaded)."""
OPTIONAL = {
    "eclipse-zenoh": "only the deploy bridge imports it",
    "mujoco-studio": "MuJoCo's viewer and Filament renderer; `import mujoco` works without it",
}
"""Downloaded, but carried only where the calls that the others need have room."""

GPU_MACHINE_HAS = frozenset(
    """absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build
    certifi charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core
    cuda-pathfinder cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock
    flatbuffers flax fonttools formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx
    huggingface-hub humanize hypothesis idna imageio iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin
    jaxlib jaxtyping jinja2 joblib kiwisolver lazy-loader lightning lightning-utilities linear-operator lineax
    llvmlite lxml markdown markdown-it-py markupsafe matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack
    multidict multipledispatch mypy-extensions nanobind narwhals networkx ninja numba numba-cuda numpy numpyro
    nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime nvidia-cudnn-cu13 nvidia-cufft
    nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13 nvidia-ml-py
    nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
    opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec
    patsy peft pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11
    py-cpuinfo pygments pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock
    pytest-timeout pytest-xdist python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu
    safetensors scikit-build-core scikit-image scikit-learn scipy seaborn sentencepiece sentence-transformers
    setuptools shellingham simplejson six sortedcontainers statsmodels sympy tabulate tensorboard
    tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm tokenizers toolz torch torchaudio
    torchdiffeq torch-geometric torchmetrics torchvision tqdm transformers treescope triton typer
    typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel wrapt xarray xxhash yarl
    zipp""".split()  # noqa: SIM905 - a list as KINDS.md gives it
)
"""The Python packages of the GPU machine's image ('cuda'), as the workplace's KINDS.md listed them on
2026-11-17 (python3 3.12.3 with torch 2.11.0+cu130). `prepare --have FILE` replaces the list."""

TARGET_PYTHON = "3.12"
TARGET_MARKERS = {
    "python_version": "3.12",
    "python_full_version": "3.12.3",
    "implementation_name": "cpython",
    "implementation_version": "3.12.3",
    "platform_python_implementation": "CPython",
    "os_name": "posix",
    "sys_platform": "linux",
    "platform_system": "Linux",
    "platform_machine": "x86_64",
    "platform_release": "",
    "platform_version": "",
}
"""The GPU machine's interpreter, for evaluating requirement markers here."""
PLATFORMS = (
    "manylinux_2_28_x86_64",
    "manylinux_2_27_x86_64",
    "manylinux_2_24_x86_64",
    "manylinux_2_17_x86_64",
    "manylinux2014_x86_64",
    "manylinux_2_5_x86_64",
    "manylinux1_x86_64",
)
"""pip matches platform tags exactly: the glibc versions that the machine (Ubuntu 24.04, glibc 2.39)
runs and PyPI's wheels of our pins use."""


def canonical(name: str) -> str:
    """PEP 503 name: lower case, runs of -_. as one -."""
    return re.sub(r"[-_.]+", "-", name).lower()


def sha256(path: Path, chunk: int = 4 * MIB) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


# --- which packages --------------------------------------------------------------------------------
def _evaluate(marker, extra: str) -> bool:
    env = dict(TARGET_MARKERS, extra=extra)
    return marker is None or marker.evaluate(env)


def closure(
    roots: Iterable[str],
    requires_of: Callable[[str], list[str]],
    have: Iterable[str],
) -> dict[str, set[str]]:
    """Every package needed by `roots` on the target interpreter that is not in `have`:
    {canonical name: the extras asked of it}. `requires_of(name)` gives the package's
    Requires-Dist lines; extras are followed (`etils[epath]` pulls fsspec, zipp, ...)."""
    from packaging.requirements import Requirement

    have = {canonical(n) for n in have}
    needed: dict[str, set[str]] = {}
    done: dict[str, set[str]] = {}
    queue = [(canonical(r), set()) for r in roots]
    while queue:
        name, extras = queue.pop(0)
        if name in have:
            continue
        needed.setdefault(name, set()).update(extras)
        asked = needed[name]
        if name in done and asked <= done[name]:
            continue
        done[name] = set(asked)
        for line in requires_of(name):
            req = Requirement(line)
            if any(_evaluate(req.marker, e) for e in ["", *sorted(asked)]):
                queue.append((canonical(req.name), set(req.extras)))
    return needed


def installed_requires(name: str) -> list[str]:
    """Requires-Dist of the package as installed in this interpreter."""
    from importlib import metadata

    return list(metadata.distribution(name).requires or [])


def installed_version(name: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def wheel_metadata(path: Path) -> tuple[str, str, list[str]]:
    """(name, version, Requires-Dist lines) from a wheel's METADATA."""
    from email.parser import HeaderParser

    with zipfile.ZipFile(path) as z:
        meta = next(n for n in z.namelist() if re.fullmatch(r"[^/]+\.dist-info/METADATA", n))
        msg = HeaderParser().parsestr(z.read(meta).decode("utf-8", "replace"))
    return msg["Name"], msg["Version"], list(msg.get_all("Requires-Dist") or [])


def wheel_name(filename: str) -> tuple[str, str]:
    """(canonical distribution, version) from a wheel file name."""
    parts = filename.split("-")
    if not filename.endswith(".whl") or len(parts) < 5:
        raise ValueError(f"not a wheel file name: {filename}")
    return canonical(parts[0]), parts[1]


def read_have(path: Path) -> set[str]:
    """Package names, one a line, or `pip list` / `pip freeze` output."""
    names = set()
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", "Package", "---")):
            continue
        names.add(canonical(re.split(r"[\s=<>!~@;\[]", line, maxsplit=1)[0]))
    return names


# --- transfers -------------------------------------------------------------------------------------
@dataclasses.dataclass
class Piece:
    """One file that travels: a whole wheel, or part `index` of it."""

    wheel: str
    call: int
    file: str
    offset: int
    size: int
    sha256: str = ""


@dataclasses.dataclass
class Plan:
    capacity: int
    calls: int
    pieces: list[Piece]
    left_behind: dict[str, str]


def plan_transfers(sizes: dict[str, int], optional: Iterable[str], capacity: int, part_max: int = PART_MAX) -> Plan:
    """Pack wheels {file: bytes} into as few calls of `capacity` bytes as the required
    ones need: small files whole, in order, and a file that does not fit the room left
    cut into parts (at most `part_max` bytes each) that continue in the next calls.
    Optional files go whole into room the required ones left, or stay behind."""
    if capacity < MIB:
        raise ValueError(f"a call has {capacity / MIB:.1f} MiB of room: the working tree leaves too little")
    optional = set(optional)
    required = sorted((f for f in sizes if f not in optional), key=lambda f: (sizes[f], f))
    pieces: list[Piece] = []
    call, room = 1, capacity
    for f in required:
        size = sizes[f]
        if room == 0:
            call, room = call + 1, capacity
        if size <= room and size <= part_max:
            pieces.append(Piece(f, call, f, 0, size))
            room -= size
            continue
        offset, index = 0, 0
        while offset < size:
            if room == 0:
                call, room = call + 1, capacity
            n = min(size - offset, room, part_max)
            index += 1
            pieces.append(Piece(f, call, f"{f}.part{index:02d}", offset, n))
            offset, room = offset + n, room - n
    calls = call if pieces else 0
    used = {c: sum(p.size for p in pieces if p.call == c) for c in range(1, calls + 1)}
    left_behind = {}
    for f in sorted(optional & set(sizes), key=lambda f: (sizes[f], f)):
        fit = next((c for c in range(1, calls + 1) if used[c] + sizes[f] <= capacity), None)
        if fit is None or sizes[f] > part_max:
            left_behind[f] = "no room left in the calls the other wheels need"
            continue
        pieces.append(Piece(f, fit, f, 0, sizes[f]))
        used[fit] += sizes[f]
    return Plan(capacity, calls, sorted(pieces, key=lambda p: (p.call, p.file)), left_behind)


def write_pieces(src: Path, dest: Path, pieces: list[Piece]) -> None:
    """Write each piece of the wheels in `src` to dest/call<k>/<file>; a piece already
    there with the right size and hash is kept. Fills in each piece's sha256."""
    for p in pieces:
        out = dest / f"call{p.call}" / p.file
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(src / p.wheel, "rb") as f:
            f.seek(p.offset)
            data = f.read(p.size)
        digest = hashlib.sha256(data).hexdigest()
        if not (out.is_file() and out.stat().st_size == p.size and sha256(out) == digest):
            tmp = out.with_name(out.name + ".tmp")
            tmp.write_bytes(data)
            os.replace(tmp, out)
        p.sha256 = digest


def join_wheel(entry: dict, stash: Path, dest: Path) -> Path:
    """Rebuild one wheel of the manifest from its pieces in `stash` into `dest`, checking
    every piece's and the whole file's sha256. Raises FileNotFoundError / ValueError."""
    out = dest / entry["file"]
    if out.is_file() and out.stat().st_size == entry["size"] and sha256(out) == entry["sha256"]:
        return out
    dest.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    h = hashlib.sha256()
    with open(tmp, "wb") as w:
        for piece in entry["pieces"]:
            data = (stash / piece["file"]).read_bytes()
            if hashlib.sha256(data).hexdigest() != piece["sha256"]:
                raise ValueError(f"{piece['file']} (call {piece['call']}) is damaged: its sha256 differs")
            h.update(data)
            w.write(data)
    if h.hexdigest() != entry["sha256"]:
        tmp.unlink()
        raise ValueError(f"{entry['file']}: the joined parts do not give the wheel's sha256")
    os.replace(tmp, out)
    return out


def tree_bytes(repo: Path) -> int:
    """Bytes of what a device call sends of the checkout: tracked and untracked-not-ignored
    files, plus shared/ (sent even where ignored)."""
    out = subprocess.run(
        ["git", "-C", str(repo), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        capture_output=True,
        check=True,
    ).stdout
    total, seen = 0, set()
    for rel in out.decode().split("\0"):
        p = repo / rel
        if rel and p.is_file() and not p.is_symlink():
            seen.add(p.resolve())
            total += p.stat().st_size
    shared = repo / "shared"
    if shared.is_dir():
        for p in shared.rglob("*"):
            if p.is_file() and not p.is_symlink() and p.resolve() not in seen:
                total += p.stat().st_size
    return total


# --- prepare (here) --------------------------------------------------------------------------------
def pip_download(python: str, dest: Path, specs: list[str]) -> None:
    cmd = [python, "-m", "pip", "download", "--disable-pip-version-check", "--no-deps", "--only-binary=:all:"]
    cmd += ["--python-version", TARGET_PYTHON, "--implementation", "cp"]
    for tag in PLATFORMS:
        cmd += ["--platform", tag]
    cmd += ["-d", str(dest), *specs]
    subprocess.run(cmd, check=True)


def _wheel_files(folder: Path) -> dict[str, Path]:
    found = {}
    if folder.is_dir():
        for p in folder.glob("*.whl"):
            found[wheel_name(p.name)[0]] = p
    return found


def prepare(
    repo: Path,
    *,
    dry_run: bool = False,
    have: set[str] | None = None,
    python: str | None = None,
    log=print,
) -> dict:
    """Download the missing wheels (the versions installed here), pack them into
    per-call folders under <repo>/.whl and write the manifest. Returns the manifest."""
    have = set(GPU_MACHINE_HAS if have is None else have)
    root = repo / WHEEL_DIR
    store = root / "wheels"
    old = {}
    if (root / MANIFEST).is_file():
        old = {w["file"]: w for w in json.loads((root / MANIFEST).read_text()).get("wheels", [])}

    needed = closure(ROOTS, installed_requires, have)
    pins = {}
    for name in sorted(needed):
        version = installed_version(name)
        if version is None:
            raise RuntimeError(f"{name} is needed on the GPU machine but not installed here: no version to pin")
        pins[name] = version
    if dry_run:
        log(f"[prepare] {len(pins)} packages the GPU machine lacks (versions installed here):")
        for name, version in pins.items():
            note = f"  ({OPTIONAL[name]}: carried if there is room)" if name in OPTIONAL else ""
            log(f"  {name}=={version}{note}")
        for name, why in NOT_CARRIED.items():
            log(f"  not carried: {name} ({why})")
        return {"packages": pins}

    store.mkdir(parents=True, exist_ok=True)
    # Download, then read each wheel's own METADATA: its needs on Python 3.12 decide the rest.
    wanted = dict(pins)
    while True:
        present = _wheel_files(store)
        for name, path in list(present.items()):
            if name not in wanted or wheel_name(path.name)[1] != wanted[name]:
                path.unlink()  # a version no longer pinned, or no longer needed
                del present[name]
                continue
            entry = old.get(path.name)
            if entry and (path.stat().st_size != entry["size"] or sha256(path) != entry["sha256"]):
                log(f"[prepare] {path.name}: hash differs from the manifest, downloading again")
                path.unlink()
                del present[name]
        missing = [f"{n}=={v}" for n, v in sorted(wanted.items()) if n not in present]
        if missing:
            log(f"[prepare] downloading {len(missing)} wheel(s): {' '.join(missing)}")
            pip_download(python or sys.executable, store, missing)
        files = _wheel_files(store)
        from_wheels = {n: wheel_metadata(p)[2] for n, p in files.items()}
        again = closure(ROOTS, lambda n, meta=from_wheels: meta.get(n) or installed_requires(n), have)
        extra = sorted(set(again) - set(wanted))
        if not extra:
            break
        for name in extra:
            version = installed_version(name)
            if version is None:
                raise RuntimeError(f"wheel metadata asks for {name}, which is not installed here: no version to pin")
            wanted[name] = version
    files = _wheel_files(store)
    unknown = sorted(set(files) - set(wanted))
    for name in unknown:
        files.pop(name).unlink()

    tree = tree_bytes(repo)
    capacity = TRANSFER_LIMIT - tree - MARGIN
    sizes = {p.name: p.stat().st_size for p in files.values()}
    optional = {p.name for n, p in files.items() if n in OPTIONAL}
    plan = plan_transfers(sizes, optional, capacity)
    expected = {(f"call{p.call}", p.file) for p in plan.pieces}
    for folder in root.glob("call*"):
        if not folder.is_dir():
            continue
        if not any(c == folder.name for c, _ in expected):
            shutil.rmtree(folder)
            continue
        for f in folder.iterdir():
            if f.name != MANIFEST and (folder.name, f.name) not in expected:
                f.unlink()
    write_pieces(store, root, plan.pieces)
    wheels = []
    for name, path in sorted(files.items()):
        digest = old[path.name]["sha256"] if path.name in old and old[path.name]["size"] == sizes[path.name] else None
        digest = digest or sha256(path)
        pieces = [dataclasses.asdict(p) for p in plan.pieces if p.wheel == path.name]
        wheels.append(
            {
                "file": path.name,
                "name": name,
                "version": wanted[name],
                "size": sizes[path.name],
                "sha256": digest,
                "optional": name in OPTIONAL,
                "pieces": pieces,
                "carried": bool(pieces),
            }
        )
    manifest = {
        "format": 1,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "git": _git_state(repo),
        "python": TARGET_PYTHON,
        "platforms": list(PLATFORMS),
        "tree_bytes": tree,
        "capacity": capacity,
        "calls": plan.calls,
        "wheels": wheels,
        "left_behind": {f: why for f, why in plan.left_behind.items()},
    }
    text = json.dumps(manifest, indent=1) + "\n"
    (root / MANIFEST).write_text(text)
    for c in range(1, plan.calls + 1):
        (root / f"call{c}" / MANIFEST).write_text(text)
    return manifest


def _git_state(repo: Path) -> str | None:
    """The checkout's commit, '+changes' when its tracked files differ from it."""
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(
            ["git", "-C", str(repo), "status", "--porcelain", "-uno"], capture_output=True, text=True
        )
    except OSError:
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def device_calls(manifest: dict, out_flag: str = "--out $OUT") -> list[dict]:
    """The device tool's run calls that move the wheels and run the check: each carries
    its folder; the last also installs and runs."""
    calls = []
    n = manifest["calls"]
    for c in range(1, n + 1):
        last = f"PYTHONUNBUFFERED=1 python3 dev/gpu_loan/gpu.py run {out_flag}"
        cmd = "python3 dev/gpu_loan/gpu.py stash" if c < n else last
        calls.append({"carry": [f"{WHEEL_DIR}/call{c}"], "command": cmd})
    return calls


def describe(manifest: dict) -> str:
    lines = [f"wheels for Python {manifest['python']} (x86-64 manylinux), {len(manifest['wheels'])} files:"]
    for w in manifest["wheels"]:
        where = ", ".join(f"call {p['call']}" for p in w["pieces"]) or "left behind"
        parts = f" in {len(w['pieces'])} parts" if len(w["pieces"]) > 1 else ""
        lines.append(f"  {w['size'] / MIB:7.2f} MiB  {w['file']}{parts} ({where})")
    total = sum(w["size"] for w in manifest["wheels"] if w["carried"])
    lines.append(
        f"carried: {total / MIB:.1f} MiB in {manifest['calls']} device calls of at most "
        f"{manifest['capacity'] / MIB:.1f} MiB each (64 MiB minus the working tree's "
        f"{manifest['tree_bytes'] / MIB:.1f} MiB and {MARGIN // MIB} MiB spare)"
    )
    for f, why in manifest["left_behind"].items():
        lines.append(f"left behind: {f} ({why})")
    return "\n".join(lines)


# --- the GPU side ----------------------------------------------------------------------------------
def stash(repo: Path, dest: Path, log=print) -> dict:
    """Copy the carried .whl/call<k> folders into `dest` (outside the checkout), checking
    each piece against the manifest. Returns {"present": [...], "missing": {call: [files]}}."""
    dest.mkdir(parents=True, exist_ok=True)
    manifest = None
    for folder in sorted((repo / WHEEL_DIR).glob("call*")):
        m = folder / MANIFEST
        if m.is_file():
            candidate = json.loads(m.read_text())
            if manifest is None or candidate["created"] > manifest["created"]:
                manifest = candidate
    if manifest is None and (dest / MANIFEST).is_file():
        manifest = json.loads((dest / MANIFEST).read_text())
    if manifest is None:
        raise FileNotFoundError(f"no {WHEEL_DIR}/call<k>/{MANIFEST} here and none stashed in {dest}")
    (dest / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    present, missing = [], {}
    for w in manifest["wheels"]:
        for p in w["pieces"]:
            target = dest / p["file"]
            src = repo / WHEEL_DIR / f"call{p['call']}" / p["file"]
            have_it = target.is_file() and target.stat().st_size == p["size"] and sha256(target) == p["sha256"]
            if not have_it and src.is_file() and src.stat().st_size == p["size"] and sha256(src) == p["sha256"]:
                shutil.copyfile(src, target)
            if target.is_file() and target.stat().st_size == p["size"]:
                present.append(p["file"])
            else:
                missing.setdefault(p["call"], []).append(p["file"])
    log(f"[stash] {dest}: {len(present)} of {len(present) + sum(map(len, missing.values()))} pieces present")
    for call, files in sorted(missing.items()):
        log(f"[stash] missing, carried by call {call}: {' '.join(files)}")
    return {"manifest": manifest, "present": present, "missing": missing}


def install(repo: Path, stash_dir: Path, site: Path, python: str | None = None, log=print) -> dict:
    """Stash what this call carried, join every wheel whose pieces are all here, and
    install them with pip into `site` (no index, no deps). Idempotent: a site already
    holding this manifest's wheels is kept."""
    t0 = time.time()
    st = stash(repo, stash_dir, log)
    manifest = st["manifest"]
    joined, problems = [], []
    for w in manifest["wheels"]:
        if not w["pieces"]:
            continue
        try:
            joined.append(join_wheel(w, stash_dir, stash_dir / "joined"))
        except (OSError, ValueError) as err:
            problems.append(f"{w['file']}: {err}")
    required_missing = [
        w["file"] for w in manifest["wheels"] if not w["optional"] and w["file"] not in {p.name for p in joined}
    ]
    stamp = site / ".legged_casters_wheels"
    key = hashlib.sha256("".join(sorted(p.name for p in joined)).encode()).hexdigest()
    installed_now = False
    if not (stamp.is_file() and stamp.read_text() == key):
        cmd = [python or sys.executable, "-m", "pip", "install", "-q", "--disable-pip-version-check", "--no-index"]
        cmd += ["--no-deps", "--no-compile", "--no-cache-dir", "--upgrade", "--target", str(site)]
        proc = subprocess.run([*cmd, *map(str, joined)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"pip install failed ({proc.returncode}): {(proc.stderr or proc.stdout)[-3000:]}")
        stamp.write_text(key)
        installed_now = True
    log(f"[install] {len(joined)} wheels in {site} ({'installed' if installed_now else 'already there'})")
    return {
        "status": "ok" if not required_missing and not problems else "incomplete",
        "prepared": {k: manifest.get(k) for k in ("created", "git", "calls")},
        "left_behind": sorted(wheel_name(f)[0] for f in manifest.get("left_behind", {})),
        "site": str(site),
        "wheels": [p.name for p in joined],
        "missing_required": required_missing,
        "problems": problems,
        "missing_pieces": st["missing"],
        "seconds": round(time.time() - t0, 1),
    }


def check_requirements(site: Path, left_behind: Iterable[str] = ()) -> list[str]:
    """Unmet Requires-Dist (no extras) of the packages in `site`, looked up in `site` and
    then this interpreter's own packages: what pip's resolver would have complained of,
    less the optional packages `prepare` left behind on purpose."""
    from importlib import metadata

    from packaging.requirements import Requirement

    env_paths = [str(site), *sys.path]
    versions = {}
    for dist in metadata.distributions(path=env_paths):
        versions.setdefault(canonical(dist.metadata["Name"]), dist.version)
    problems = []
    skip = {canonical(n) for n in left_behind}
    for dist in metadata.distributions(path=[str(site)]):
        for line in dist.requires or []:
            req = Requirement(line)
            if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                continue
            if canonical(req.name) in skip:
                continue
            have = versions.get(canonical(req.name))
            if have is None:
                problems.append(f"{dist.metadata['Name']} needs {req}: not installed")
            elif req.specifier and not req.specifier.contains(have, prereleases=True):
                problems.append(f"{dist.metadata['Name']} needs {req}: {have} installed")
    return sorted(set(problems))
