"""Keeping freed memory for reuse: the examples run under glibc tunables that stop ``malloc``
from handing every large tensor back to the kernel.

By default glibc serves each allocation above its mmap threshold (at most 32 MiB) with a fresh
``mmap`` and unmaps it when freed, so every large tensor is page-faulted in again: the frozen
encoder's 70k clouds (``[1024, 512, 256]`` fp32 activations, 0.5 GiB each) took 3.7x longer
than with the memory kept, and a policy training step 1.4x longer, most of it kernel time. The
tunables only take effect at process start, hence :func:`reuse_freed_memory` re-executes the
script once with them set; child processes (collector workers, torchrun ranks) inherit them.
Results do not change (the same kernels on the same values). ``DALIR_MALLOC=system`` turns it off.
"""

from __future__ import annotations

import os
import platform
import sys

# Allocations up to 4 GiB come from the heap and freed memory stays there for reuse.
MALLOC_TUNABLES = "glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=4294967296"
OPT_OUT = "DALIR_MALLOC"  # "system": keep the C library's defaults


def tuned_environment(environ: dict[str, str] | None = None) -> dict[str, str] | None:
    """The environment to re-execute with, or ``None`` when there is nothing to do (not glibc
    Linux, opted out, or the tunables already set by the user or a previous re-execution)."""
    environ = dict(os.environ if environ is None else environ)
    tunables = environ.get("GLIBC_TUNABLES", "")
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc" or environ.get(OPT_OUT) == "system" or "glibc.malloc.mmap_threshold" in tunables:
        return None
    environ["GLIBC_TUNABLES"] = f"{tunables}:{MALLOC_TUNABLES}" if tunables else MALLOC_TUNABLES
    return environ


def reuse_freed_memory() -> None:
    """Re-executes this Python process (same interpreter, flags and arguments) under
    :data:`MALLOC_TUNABLES` unless :func:`tuned_environment` says there is nothing to do. Call it
    first in a script's ``__main__`` block, never from library code."""
    environ = tuned_environment()
    if environ is None:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], environ)
