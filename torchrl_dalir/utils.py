"""Small shared helpers: atomic file writes, safe loading of torch files."""

from __future__ import annotations

import os
import pickle
import re
import tempfile
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
    except OSError:  # missing file, a directory, ...: the message already names the path
        raise
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
