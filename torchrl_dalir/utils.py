"""Small shared helpers: atomic file writes, safe loading of torch files, digests of weights, logged job processes."""

from __future__ import annotations

import hashlib
import os
import pickle
import re
import subprocess
import tempfile
import time
from pathlib import Path

import torch


def atomic_write_text(path: str | Path, text: str) -> None:
    """Writes ``text`` to ``path`` so that a crash leaves either the old file or the new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def writable_dir(path: str | Path, setting: str = "out") -> Path:
    """Creates the folder ``path`` (and its parents) and checks that files can be written in it,
    before a job spends time on results it could not save; a ``ValueError`` names the folder and
    the ``setting`` to change otherwise."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as error:
        raise ValueError(f"cannot write results to the folder {path} ({error.strerror or error}): "
                         f"pass {setting}=<a folder you can write to>") from None
    return path


class UnsafeFileError(ValueError):
    """A torch file holds a pickled object other than tensors and plain values: loading it could run code."""


def safe_torch_load(path: str | Path, what: str = "torch file"):
    """``torch.load`` (on the CPU) of a file of tensors and plain values (dict, list, tuple, str,
    numbers, bool, None), with ``weights_only``: any other pickled object is refused instead of
    built, as building it can run code planted in the file. Every error names ``path`` (and says
    it is not a ``what`` if it is no torch file at all)."""
    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except OSError as error:
        if error.filename is not None:  # missing file, a directory, ...: the message already names the path
            raise
        cause = error  # the zip reader's "Invalid argument" for a truncated archive
    except pickle.UnpicklingError as error:  # a refused object, or no pickle at all (a JSON file, ...)
        cause = error.__context__ or error  # the inner error: torch's own message suggests weights_only=False
        refused = re.search(r"GLOBAL (\S+)", str(cause))
        if refused:
            raise UnsafeFileError(
                f"refused to load {path}: it holds a pickled {refused[1].rstrip('.')}, not only tensors and plain values, "
                "and loading it could run code. Checkpoints of this library hold none: if this one was written by an "
                "older version, retrain it; otherwise do not trust the file"
            ) from None
    except Exception as error:  # a truncated zip archive, an empty file, ...
        cause = error
    raise ValueError(f"{path} is not a {what}, or is truncated: {str(cause) or type(cause).__name__}") from cause


def weights_digest(module: torch.nn.Module) -> str:
    """A SHA-256 hex digest of a module's state dict (every entry's name, dtype, shape and bytes, in
    key order): equal for the same weights, loaded anywhere, and different for any other weights."""
    digest = hashlib.sha256()
    for name, value in module.state_dict().items():
        value = value.detach().cpu().contiguous()
        digest.update(f"{name}:{value.dtype}:{tuple(value.shape)};".encode())
        digest.update(value.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def run_logged(command: list[str], log: str | Path, threads: int = 1) -> tuple[int, float]:
    """Runs ``command`` as its own process with ``threads`` torch threads, appending its output to
    ``log``; returns its exit code and wall time in seconds. A job that crashes stops no other."""
    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    start = time.perf_counter()
    with log.open("a") as stream:
        code = subprocess.run(command, stdout=stream, stderr=subprocess.STDOUT, env=env).returncode
    return code, time.perf_counter() - start
