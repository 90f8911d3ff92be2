"""Checkpoint files: written atomically, read with ``weights_only`` and checked for what they must hold.

Every checkpoint of the library (policy, world model, a training run's resumable state) is a dict
of tensors and plain values written by :func:`save_checkpoint` and read by :func:`load_checkpoint`
(or :func:`safe_torch_load` for files of other kinds): a file that holds any other pickled object
is refused, never built, since building it could run code planted in it.
"""

from __future__ import annotations

import functools
import pickle
import re
from pathlib import Path

import torch
from torch import nn

from torchrl_dalir.utils import atomic_write


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
                f"refused to load {path}: it holds a pickled {refused[1].rstrip('.')}, "
                "not only tensors and plain values, "
                "and loading it could run code. Checkpoints of this library hold none: if this one was written by an "
                "older version, retrain it; otherwise do not trust the file"
            ) from None
    except Exception as error:  # a truncated zip archive, an empty file, ...
        cause = error
    raise ValueError(f"{path} is not a {what}, or is truncated: {str(cause) or type(cause).__name__}") from cause


def save_checkpoint(path: str | Path, payload: dict) -> None:
    """``torch.save`` of ``payload`` through :func:`~torchrl_dalir.utils.atomic_write`: a crash while
    writing leaves the previous checkpoint, never half of one.

    Args:
        path: the checkpoint file.
        payload: tensors and plain values only (what :func:`safe_torch_load` reads back).

    Example:
        >>> import tempfile, torch
        >>> path = Path(tempfile.mkdtemp()) / "checkpoint.pt"
        >>> save_checkpoint(path, {"kind": "policy", "step": 3})
        >>> load_checkpoint(path, "policy", ("step",))["step"]
        3
    """
    atomic_write(path, functools.partial(torch.save, payload))


def check_entries(state: dict, path: str | Path, entries, what: str) -> None:
    """Refuses a loaded checkpoint that lacks any of ``entries``, naming the file and the entries
    (instead of a bare ``KeyError`` later)."""
    missing = [entry for entry in entries if entry not in state]
    if missing:
        raise ValueError(
            f"{path} is a damaged or incomplete {what}: it has no {', '.join(map(repr, missing))} "
            f"entr{'y' if len(missing) == 1 else 'ies'}. Write it again (train the stage again, or copy the file anew)"
        )


def load_checkpoint(path: str | Path, kind: str, entries=()) -> dict:
    """Loads a checkpoint written by this library and checks that it holds a ``kind`` model with
    every one of ``entries``. Refuses (:class:`UnsafeFileError`) a file holding anything but
    tensors and plain values, before looking at its kind.

    Args:
        path: the checkpoint file (a folder is refused with the ``.pt`` files in it named).
        kind: ``"policy"`` or ``"world_model"``, the file's ``kind`` entry.
        entries: the entries it must hold.
    """
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.pt"))
        raise IsADirectoryError(
            f"{path} is a directory; pass the {kind} checkpoint file in it ({[p.name for p in found] or 'none found'})"
        )
    if not path.exists():
        raise FileNotFoundError(f"no {kind} checkpoint at {path}")
    state = safe_torch_load(path, f"torchrl_dalir {kind} checkpoint")
    if not isinstance(state, dict) or state.get("kind") != kind:
        raise ValueError(f"{path} is not a torchrl_dalir {kind} checkpoint")
    check_entries(state, path, entries, f"{kind} checkpoint")
    return state


def load_weights(module: nn.Module, state: dict, entry: str, path: str | Path) -> None:
    """``module.load_state_dict(state[entry])``; weights that do not fit the module are reported with the file."""
    try:
        module.load_state_dict(state[entry])
    except RuntimeError as error:
        raise ValueError(
            f"{path}: the weights in {entry!r} do not fit the model the checkpoint describes: {str(error).strip()}"
        ) from None


def training_finished(checkpoint_path: str | Path) -> bool:
    """Whether a training run's checkpoint (:func:`~torchrl_dalir.training.fit`'s) exists and
    holds its last step (not an interrupted run)."""
    path = Path(checkpoint_path)
    if not path.exists():
        return False
    state = safe_torch_load(path)
    if not isinstance(state, dict):
        raise ValueError(f"{path} is not a torchrl_dalir training checkpoint")
    return state.get("step", 0) >= state.get("num_steps", float("inf"))
