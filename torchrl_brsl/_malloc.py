"""Which ``malloc`` serves this process: the compiled plan loops' speed depends on it.

Inductor's C++ code allocates every intermediate tensor of every step of a plan's loop (about a hundred
small buffers a step) through ``posix_memalign``, which glibc serves outside its per-thread cache: on the
bicycle's compiled plan at batch 1, a quarter of the loop's time was spent in glibc's ``malloc`` and ``free``
(``perf``). A caching allocator preloaded into the process (``LD_PRELOAD``; tcmalloc, jemalloc) removes most of
it; ``docs/install.md`` has the figures. Benchmarks print :func:`malloc_name` so that their timings say which
allocator they ran on.
"""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

ALLOCATORS = {"libtcmalloc": "tcmalloc", "libjemalloc": "jemalloc", "libmimalloc": "mimalloc"}
"""Library name prefixes of the caching allocators recognised, and their names."""

LIBRARIES = {"tcmalloc": "libtcmalloc_minimal.so.4", "jemalloc": "libjemalloc.so.2", "mimalloc": "libmimalloc.so.2"}
"""The shared library to preload for each allocator (the names Debian's packages install)."""


def malloc_name(maps: str | Path = "/proc/self/maps") -> str:
    """The caching allocator mapped into this process, ``"system malloc"`` if none, ``"unknown"`` without ``maps``.

    Args:
        maps: the process's memory map (Linux ``/proc/self/maps``), each line ending in the mapped file's path.

    Examples:
        >>> malloc_name() in {*ALLOCATORS.values(), "system malloc", "unknown"}
        True
    """
    try:
        lines = Path(maps).read_text().splitlines()
    except OSError:  # not Linux, or no procfs
        return "unknown"
    names = {Path(line.split()[-1]).name for line in lines if "/" in line}
    for prefix, name in ALLOCATORS.items():
        if any(file.startswith(prefix) for file in names):
            return name
    return "system malloc"


def installed_allocators() -> dict[str, str]:
    """``{name: path}`` of the caching allocators the dynamic linker knows (``ldconfig -p``), for ``LD_PRELOAD``.

    Examples:
        >>> set(installed_allocators()) <= set(LIBRARIES)
        True
    """
    ldconfig = shutil.which("ldconfig") or "/sbin/ldconfig"
    try:
        listing = subprocess.run([ldconfig, "-p"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):  # no ldconfig (not glibc Linux)
        return {}
    listed = {}  # library file name -> path, the first listing of each
    for line in listing.splitlines():
        library, arrow, path = line.strip().partition(" => ")
        if arrow:
            listed.setdefault(library.split()[0], path.strip())
    return {name: listed[file] for name, file in LIBRARIES.items() if file in listed}
