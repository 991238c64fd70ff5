"""Which malloc serves the process (``torchrl_brsl._malloc``), read from its memory map."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_brsl._malloc import installed_allocators, malloc_name

LIBC = "7f0000000000-7f0000001000 r-xp 00000000 08:01 42 /usr/lib/x86_64-linux-gnu/libc.so.6\n"
ANONYMOUS = "7ffd00000000-7ffd00021000 rw-p 00000000 00:00 0 [stack]\n"


@pytest.mark.parametrize("library, name", [("libtcmalloc_minimal.so.4.5.10", "tcmalloc"),
                                           ("libjemalloc.so.2", "jemalloc"), (None, "system malloc")])
def test_names_the_mapped_allocator(tmp_path, library, name):
    lines = LIBC + ANONYMOUS
    if library is not None:
        lines += f"7f0000002000-7f0000003000 r-xp 00000000 08:01 43 /opt/lib/{library}\n"
    (tmp_path / "maps").write_text(lines)
    assert malloc_name(tmp_path / "maps") == name


def test_unknown_without_a_memory_map(tmp_path):
    assert malloc_name(tmp_path / "missing") == "unknown"


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="no /proc/self/maps (not Linux)")
def test_reads_this_process_and_a_preloaded_one():
    probe = [sys.executable, "-c", "from torchrl_brsl._malloc import malloc_name; print(malloc_name())"]
    plain = {key: value for key, value in os.environ.items() if key != "LD_PRELOAD"}
    assert subprocess.run(probe, capture_output=True, text=True, env=plain, check=True).stdout.strip() \
        == "system malloc"
    library = installed_allocators().get("tcmalloc")
    if library is None:
        pytest.skip("tcmalloc is not installed (libtcmalloc-minimal4)")
    preloaded = subprocess.run(probe, capture_output=True, text=True, env={**plain, "LD_PRELOAD": library},
                               check=True)
    assert preloaded.stdout.strip() == "tcmalloc"


def test_finds_the_allocators_the_linker_lists(monkeypatch):
    lib = "/lib/x86_64-linux-gnu"
    listing = ("3 libs found in cache `/etc/ld.so.cache'\n"
               f"\tlibtcmalloc_minimal_debug.so.4 (libc6,x86-64) => {lib}/libtcmalloc_minimal_debug.so.4\n"
               f"\tlibtcmalloc_minimal.so.4 (libc6,x86-64) => {lib}/libtcmalloc_minimal.so.4\n"
               "\tlibjemalloc.so.2 (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/libjemalloc.so.2\n")
    monkeypatch.setattr(subprocess, "run", lambda *args, **kwargs: subprocess.CompletedProcess(args, 0, listing, ""))
    assert installed_allocators() == {"tcmalloc": f"{lib}/libtcmalloc_minimal.so.4",
                                      "jemalloc": "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2"}

    def missing(*args, **kwargs):
        raise FileNotFoundError("ldconfig")
    monkeypatch.setattr(subprocess, "run", missing)
    assert installed_allocators() == {}
