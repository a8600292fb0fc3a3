"""Pack the project's own install (its Python 3.11, the venv's packages a run opens, Blender's GPU kernels, the system
libraries they load) into parts small enough to carry to a GPU machine that reaches no package registry.

Such a machine (the device tool's) has another Python (3.12: no bpy wheel), no Blender, maybe no X11/GL libraries,
and takes 64 MiB a call. What to pack is found, not guessed: `strace` records every file that `omnidata generate`
opens on the real rooms (here, on the CPU); each small package that was touched goes whole, bpy and scipy file by
file (numba, llvmlite and numpy whole: a new machine compiles the kernels), plus the Cycles kernels only a GPU
loads: the OptiX modules and a cubin for the GPU's architecture. Blender's wheel ships none for Hopper, so the
driver would JIT its compute_75 PTX on that machine (the compile that takes ptxas 15 minutes of one core here);
`--sm 90` builds it here once with ptxas, kept in ~/.cache/omnidata-gpu. bpy's module and llvmlite lose their symbol tables.
The parts unpack at the same absolute paths (the interpreter's RUNPATH and prefix are absolute).

On the GPU machine, one call a part, each within the 30 s that machine stays warm (scripts/device_run.sh):
  run "bash scripts/device_run.sh probe"  carry [".gpu/part_00"]       (starts the machine; what it has)
  run "bash scripts/device_run.sh stage"  carry [".gpu/part_0N"]       (each middle part)
  run "bash scripts/device_run.sh run"    carry [the last part]        (unpacks; oracle tests;
                                                                        bench/render/gpu_cost.py)
Measured (2026-11-28): 6 parts of 50 MiB (282 MiB packed), each staging call ~4 s of device time, the unpack 4 s;
the cubin took ptxas 13.5 minutes here, the bundle 6.5 minutes (strace runs and xz).
Run: .venv/bin/python scripts/device_bundle.py [--sm 90 | --cubin PATH] [--out .gpu] [--part-mib 50]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench" / "render"))
from room_cost import ROOMS, SCENES  # noqa: E402  (the real rooms the benchmarks run: their files are what a run opens)

ROOT = Path(__file__).resolve().parents[1]
PREFIX = Path(sys.base_prefix)  # the interpreter the venv was made from (pyenv's 3.11)
SITE = Path(next(p for p in sys.path if p.endswith("site-packages") and p.startswith(str(ROOT))))
BIG = {"bpy", "scipy"}  # packed file by file; numba compiles on a new machine: it, llvmlite and numpy go whole
# The oracle tests' runner, and OpenEXR (they read a position EXR back; so does a ZIP-compressed position).
EXTRA_PACKAGES = ("pytest", "_pytest", "pluggy", "iniconfig", "packaging", "pygments", "pytest_timeout.py", "py.py",
                  "OpenEXR.cpython-311-x86_64-linux-gnu.so")
STDLIB_SKIP = {"test", "idlelib", "tkinter", "turtledemo", "ensurepip", "lib2to3", "site-packages", "__pycache__",
               "config-3.11-x86_64-linux-gnu"}  # the last: the static libpython, for building extensions
STRIP = {"__init__.so", "libllvmlite.so"}
GLIBC = re.compile(r"lib(c|m|dl|rt|pthread|util|resolv|stdc\+\+|gcc_s)\.so")
BLENDER_DIRS = ("bpy/4.5/scripts/startup", "bpy/4.5/scripts/modules")
CYCLES_LIB = "bpy/4.5/scripts/addons_core/cycles/lib"
TEST_SCENES = ("ycb_banana", "stanford_bunny")  # tests/worker/blender/test_render.py's objects (its room is ICL's)
GPU_KERNELS = ("kernel_compute_75.ptx.zst", "kernel_optix.ptx.zst", "kernel_optix_shader_raytrace.ptx.zst")


def traced_files(tmp: Path) -> set[Path]:
    """Every regular file `omnidata generate` opened on the two rooms (1 point, 3 views, every default cue)."""
    spec = tmp / "spec.json"
    spec.write_text('{"points": {"count": 1, "max_views": 3}, "views": {"resolution": 64}}')
    opened: set[Path] = set()
    for i, (space, extra) in enumerate(ROOMS.values()):
        log = tmp / f"trace{i}.txt"
        subprocess.run(["strace", "-f", "-z", "-e", "trace=openat,open,execve", "-o", str(log), sys.executable,
                        "-m", "services.cli", "generate", str(space), *extra, "--out", str(tmp / f"out{i}"), "--spec", str(spec),
                        "--no-progress", "--workers", "1"], cwd=ROOT, check=True, capture_output=True)
        for line in log.read_text().splitlines():
            match = re.search(r'open(?:at)?\((?:AT_FDCWD, )?"([^"]+)".*= \d+$', line)
            path = Path(os.path.normpath(ROOT / match.group(1))) if match else None
            if path and path.is_file():  # as opened: a system library by the name the loader asked for (its soname)
                opened.add(path)
    return opened


def select(opened: set[Path], cubin: Path, tmp: Path) -> tuple[list[tuple[Path, str]], list[Path]]:
    """(file, name in the archive) pairs of the install, and the system libraries it loaded."""
    members: dict[str, Path] = {}

    def add(path: Path) -> None:  # a file or a folder of the interpreter, at its own path
        if path.is_file() and "__pycache__" not in path.parts:
            members[str(path)] = path
        elif path.is_dir():
            for sub in path.rglob("*"):
                if sub.is_file() and "__pycache__" not in sub.parts:
                    members[str(sub)] = sub

    add(PREFIX / "bin" / "python3.11")
    for lib in (PREFIX / "lib").glob("libpython3*.so*"):
        add(lib)
    stdlib = PREFIX / "lib" / "python3.11"
    for entry in stdlib.iterdir():
        if entry.name not in STDLIB_SKIP:
            add(entry)
    # The venv's packages go into the interpreter's own site-packages on that machine (no venv there).
    target = stdlib / "site-packages"
    touched = {top_level(p.relative_to(SITE)) for p in opened if p.is_relative_to(SITE)}
    touched |= {p.name for p in SITE.glob("*.py")}  # single-file modules are small: all of them
    for top in sorted(touched | set(EXTRA_PACKAGES)):
        path = SITE / top
        if top.endswith(".pth") or top in BIG or not path.exists():
            continue
        for sub in ([path] if path.is_file() else [s for s in path.rglob("*") if s.is_file()]):
            if "__pycache__" not in sub.parts:
                members[str(target / sub.relative_to(SITE))] = sub
    big = [p for p in opened if p.is_relative_to(SITE) and p.relative_to(SITE).parts[0] in BIG]
    big += [p.parent.parent / (p.name.split(".")[0] + ".py") for p in big if p.parent.name == "__pycache__"]
    big += [p for d in BLENDER_DIRS for p in (SITE / d).rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    for path in big:  # with each bytecode file's source, which the import system needs beside it
        if path.is_file():
            members[str(target / path.relative_to(SITE))] = path
    for libs in SITE.glob("*.libs"):  # the libraries auditwheel vendored beside a package that was loaded
        if libs.name.split(".")[0].replace("pillow", "PIL") not in touched | BIG:
            continue
        for sub in libs.iterdir():
            members[str(target / sub.relative_to(SITE))] = sub
    for name in GPU_KERNELS:
        members[str(target / CYCLES_LIB / name)] = SITE / CYCLES_LIB / name
    packed = tmp / f"{cubin.stem}.cubin.zst"  # kernel_sm_90.cubin.zst: the name Cycles looks for first
    subprocess.run(["zstd", "-q", "-19", "-f", str(cubin), "-o", str(packed)], check=True)
    members[str(target / CYCLES_LIB / packed.name)] = packed
    system = sorted({p.name: p for p in opened if str(p).startswith(("/lib/", "/usr/lib/")) and ".so" in p.name
                     and not GLIBC.match(p.name) and "ld-linux" not in p.name}.values())
    # The rooms bench/render/gpu_cost.py runs there (--scenes /root/od-scenes; bench/scans/ travels with the
    # tree), and the
    # oracle tests' scenes.
    for path in [path for path, _ in ROOMS.values() if path.is_relative_to(SCENES)] + [SCENES / n for n in TEST_SCENES]:
        for sub in ([path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())):
            members[f"/root/od-scenes/{sub.relative_to(SCENES)}"] = sub
    return sorted((path, name) for name, path in members.items()), system


def top_level(rel: Path) -> str:
    """The site-packages entry a file belongs to (a top-level module's bytecode names its module: six.py)."""
    if rel.parts[0] == "__pycache__":
        return rel.parts[1].split(".")[0] + ".py"
    return rel.parts[0]


def stripped(path: Path, tmp: Path) -> Path:
    """The two big libraries that ship their symbol tables (bpy's module, llvmlite's LLVM: ~60 MB) without them.
    Only those: strip breaks the libraries patchelf rewrote for their wheels (load commands no longer page-aligned)."""
    if path.name not in STRIP:
        return path
    copy = tmp / "stripped" / path.name
    copy.parent.mkdir(exist_ok=True)
    subprocess.run(["strip", "--strip-unneeded", "-o", str(copy), str(path)], check=True)
    return copy


def hopper_cubin(sm: int) -> Path:
    """Cycles' CUDA kernels for compute capability `sm` (90: H100, H200), built once by ptxas from the wheel's
    compute_75 PTX into ~/.cache (about 15 minutes of one core; the same kernels the driver would JIT)."""
    cubin = Path.home() / ".cache" / "omnidata-gpu" / f"kernel_sm_{sm}.cubin"
    if not cubin.exists():
        cubin.parent.mkdir(parents=True, exist_ok=True)
        ptx = cubin.with_name("kernel_compute_75.ptx")
        subprocess.run(["zstd", "-q", "-d", "-f", str(SITE / CYCLES_LIB / "kernel_compute_75.ptx.zst"), "-o", str(ptx)],
                       check=True)
        print(f"building {cubin.name} with ptxas (about 15 minutes)", flush=True)
        subprocess.run(["ptxas", f"-arch=sm_{sm}", "-O3", str(ptx), "-o", str(cubin.with_suffix(".part"))], check=True)
        cubin.with_suffix(".part").rename(cubin)
    return cubin


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sm", type=int, default=90, help="the GPU's compute capability (90: H100, H200)")
    ap.add_argument("--cubin", type=Path, help="a kernel_sm_XX.cubin already built (default: build or reuse --sm's)")
    ap.add_argument("--out", type=Path, default=ROOT / ".gpu")
    ap.add_argument("--part-mib", type=int, default=50, help="part size: with the ~10 MiB tree, under 64 MiB a call")
    args = ap.parse_args()
    tools = ["strace", "zstd", "xz", "strip", "split"] + ([] if args.cubin else ["ptxas"])
    missing = [tool for tool in tools if shutil.which(tool) is None]
    if missing:  # strace, zstd and xz-utils are Debian packages; ptxas comes with CUDA's toolkit
        raise SystemExit(f"device_bundle: needs {', '.join(missing)} on PATH")
    args.out.mkdir(exist_ok=True)
    cubin = args.cubin or hopper_cubin(args.sm)
    with tempfile.TemporaryDirectory(prefix="omnidata-bundle-") as tmp_name:
        tmp = Path(tmp_name)
        members, system = select(traced_files(tmp), cubin, tmp)
        archive = tmp / "bundle.tar"
        with tarfile.open(archive, "w") as tar:
            for path, name in members:
                tar.add(stripped(path, tmp), arcname=name.lstrip("/"), recursive=False)
            for lib in system:
                tar.add(lib.resolve(), arcname=f"root/od-syslibs/{lib.name}")  # the file, under its soname
        size = archive.stat().st_size
        subprocess.run(["xz", "-T0", "-7", "-f", str(archive)], check=True)
        packed = archive.with_suffix(".tar.xz")
        for old in args.out.glob("part_*"):
            old.unlink()
        subprocess.run(["split", "-b", f"{args.part_mib}M", "-d", str(packed), str(args.out / "part_")], check=True)
        print(f"{len(members)} files, {len(system)} system libraries: {size / 2**20:.0f} MiB, "
              f"{packed.stat().st_size / 2**20:.0f} MiB packed, parts {sorted(p.name for p in args.out.iterdir())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
