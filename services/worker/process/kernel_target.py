"""Which CPU the compiled (numba) kernels are built for: an x86-64 level, the same on every machine that has
it.

Numba keys each cached kernel by the CPU name and feature list it was compiled for, and uses an entry only on
a machine where both match exactly. Built for the host ("znver4" and its 60 features here), a kernel cache
made when the worker image is built, or by `make venv`, is ignored on any other CPU model: each new worker
compiles all ~70 kernels again (~40 CPU-s on one core before its first view). Built for an x86-64 level, the
same cache serves every machine of that level, as fast as the host's own target where the level has the host's
vector width (bench/render/kernel_cache.py, on an AVX-512 host: x86-64-v4 as fast as the host's own code;
x86-64-v3 runs keypoints3d 10-15% slower; the baseline "generic" x86-64 costs ~18% more in all, keypoints3d
50%). A process takes the highest level its CPU has; a machine with none (or not x86-64) compiles for itself,
as numba does by default; so does one whose NUMBA_CPU_NAME is set by its operator, and a process that compiled
something with numba before this package loaded (its code generator is made once: entries cached under a level
must hold that level's code).

`select()` must run before the process compiles or loads its first kernel: the `services.worker` package calls
it on import, before any of its kernel modules loads.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Callable, Iterable, MutableMapping

# LLVM's feature names of each level (x86-64-v2's included in v3, v3's in v4; the x86-64 baseline is the
# arch's).
_V3 = frozenset({"cx16", "sahf", "popcnt", "sse3", "sse4.1", "sse4.2", "ssse3",  # v2
                 "avx", "avx2", "bmi", "bmi2", "f16c", "fma", "lzcnt", "movbe", "xsave"})
LEVELS: tuple[tuple[str, frozenset[str]], ...] = (  # best first
    ("x86-64-v4", _V3 | {"avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"}),
    ("x86-64-v3", _V3),
)


def host_features() -> frozenset[str]:
    """The CPU features LLVM sees on this machine (llvmlite, without importing numba)."""
    import llvmlite.binding as ll

    return frozenset(name for name, on in ll.get_host_cpu_features().items() if on)


def levels_for(machine: str, features: Iterable[str]) -> list[str]:
    """The levels a machine (platform.machine()) with these CPU features runs, best first."""
    if machine.lower() not in ("x86_64", "amd64"):
        return []
    have = set(features)
    return [name for name, needs in LEVELS if needs <= have]


def level_environment(level: str) -> dict[str, str]:
    """The numba settings that build kernels for `level`: its features, not the host's, so the cache key (CPU
    name, features) is the same on every machine."""
    return {"NUMBA_CPU_NAME": level, "NUMBA_CPU_FEATURES": ""}


def select(
    environ: MutableMapping[str, str] = os.environ, features: Callable[[], Iterable[str]] = host_features,
    machine: str | None = None,
) -> str | None:
    """Build kernels for the best level the host (`machine`, `features`: this one's by default) has, unless
    NUMBA_CPU_NAME is set already; returns the CPU name in force (None: numba's host default)."""
    if "NUMBA_CPU_NAME" in environ:
        return environ["NUMBA_CPU_NAME"]
    levels = levels_for(machine or platform.machine(), features())
    if not levels:
        return None
    # built for the host already: a level now would mislabel them
    if environ is os.environ and _codegen_started():
        return None
    environ.update(level_environment(levels[0]))
    if environ is os.environ and "numba.core.config" in sys.modules:  # numba read its settings already: again
        from numba.core import config

        config.reload_config()
    return levels[0]


def _codegen_started() -> bool:
    """Whether numba has made its CPU code generator in this process (it is made once, for the CPU its
    settings name then): the target context is a cached property of numba's CPU target."""
    registry = sys.modules.get("numba.core.registry")
    return registry is not None and "_toplevel_target_context" in vars(registry.cpu_target)


def load() -> None:
    """Make numba's CPU target now (its typing and lowering registries, and its code generator for the level
    `select` chose). The first kernel a process loads pays for it otherwise: ~0.4-0.6 CPU-s here, inside that
    process's first view. A worker does it while it waits for its first task; a process that forks workers
    does it once for all of them (it survives the fork; no thread is started)."""
    from numba.core.registry import cpu_target

    cpu_target.target_context.refresh()
    cpu_target.typing_context.refresh()


def load_cached_kernels(package: str = "services") -> int:
    """Load, without compiling any, every version numba's cache holds for this target of the kernels of the
    loaded modules of `package`: how many. A process that forks runs or workers does it once for all of them
    (the warm server): each would otherwise load its ~50 kernels at their first call, ~0.3 CPU-s inside its
    first view (bench/render/warm_start.py). Versions cached for another CPU, or for an older source of the
    kernel, are left alone (loading them would compile)."""
    from numba.core.dispatcher import Dispatcher
    from numba.core.registry import cpu_target

    codegen = cpu_target.target_context.codegen()
    loaded = 0
    for name, module in list(sys.modules.items()):
        if module is None or not (name == package or name.startswith(package + ".")):
            continue
        for kernel in list(vars(module).values()):
            if not isinstance(kernel, Dispatcher) or kernel.__module__ != name:
                continue  # imported from its own module, which is visited too
            cache = kernel._cache  # type: ignore[attr-defined]  # numba sets it in enable_caching()
            for key in cache._cache_file._load_index():  # {(signature, target, code hashes): file}
                if key == cache._index_key(key[0], codegen):  # this target, this source
                    kernel.compile(key[0])  # finds it in the cache: loads it
                    loaded += 1
    return loaded
