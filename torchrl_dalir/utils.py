"""Small shared helpers: required tensordict keys, atomic file writes, writable folders, digests of weights,
logged job processes, Ray."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import BinaryIO

import torch

_UMASK = os.umask(0)  # read once, at import (setting it is the only way to read it)
os.umask(_UMASK)


def require_keys(tensordict, required, reader: str) -> None:
    """Refuses ``tensordict`` unless it holds every key of ``required``, naming the missing ones, who reads
    them and the keys it does hold (a missing key otherwise surfaces deep inside as ``None``).

    Example:
        >>> from tensordict import TensorDict
        >>> require_keys(TensorDict(point_cloud=torch.zeros(2, 3), batch_size=[2]), ["point_cloud", "agent_pos"],
        ...              "RerankingActor")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        KeyError: "RerankingActor reads 'agent_pos', which the tensordict lacks (it holds ['point_cloud']); ..."
    """
    missing = [key for key in required if key not in tensordict.keys(include_nested=True)]
    if missing:
        names = ", ".join(repr(k if isinstance(k, str) else tuple(k)) for k in missing)
        held = sorted(str(k) for k in tensordict.keys(include_nested=True, leaves_only=True))
        raise KeyError(
            f"{reader} reads {names}, which the tensordict lacks (it holds {held}); pass observations as "
            "torchrl_dalir.envs.make_env gives them, or set the module's in_keys to where yours are"
        )


def atomic_write(path: str | Path, content: str | bytes | Callable[[BinaryIO], object]) -> None:
    """Writes ``path`` so that a crash or an error leaves either the old file or the new one, never
    half of one: the content goes to a temporary file next to it, is flushed to disk, then renamed
    over ``path``. The library's one way to write a file that others read (JSON, checkpoints).

    Args:
        path: the file (its folder is created if needed).
        content: text (written as UTF-8), bytes, or a function that writes to the open binary file,
            e.g. ``functools.partial(torch.save, payload)``.

    Example:
        >>> import functools, tempfile, torch
        >>> folder = Path(tempfile.mkdtemp())
        >>> atomic_write(folder / "result.json", '{"success_rate": 0.5}')
        >>> atomic_write(folder / "weights.pt", functools.partial(torch.save, {"w": torch.ones(2)}))
        >>> sorted(p.name for p in folder.iterdir())
        ['result.json', 'weights.pt']
        >>> oct((folder / "result.json").stat().st_mode & 0o777) == oct(0o666 & ~_UMASK)  # like open()'s
        True
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            if callable(content):
                content(f)
            else:
                f.write(content.encode() if isinstance(content, str) else content)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # the permissions of a file made with open(): mkstemp's are owner-only
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def measured_once(part: str | Path, inputs: dict, measure: Callable[[], dict]) -> dict:
    """``measure()``'s result, kept in the JSON file ``part`` as soon as it is measured; a later call
    with the same ``inputs`` (JSON-serialisable: what the result depends on) reads it back instead of
    measuring again, so an interrupted table resumes at the row it was measuring. Different inputs
    measure anew and replace the file.

    Example:
        >>> import tempfile
        >>> part, calls = Path(tempfile.mkdtemp()) / "parts" / "base.json", []
        >>> measure = lambda: calls.append(1) or {"success_rate": 0.5}
        >>> measured_once(part, {"episodes": 2}, measure), measured_once(part, {"episodes": 2}, measure), len(calls)
        ({'success_rate': 0.5}, {'success_rate': 0.5}, 1)
        >>> measured_once(part, {"episodes": 3}, measure) and len(calls)
        2
    """
    inputs = json.loads(json.dumps(inputs))  # as the file holds them (tuples become lists)
    part = Path(part)
    if part.exists() and (stored := json.loads(part.read_text()))["inputs"] == inputs:
        return stored["row"]
    text = json.dumps({"inputs": inputs, "row": measure()})
    atomic_write(part, text)
    return json.loads(text)["row"]  # as a later call reads it back


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
        raise ValueError(
            f"cannot write results to the folder {path} ({error.strerror or error}): "
            f"pass {setting}=<a folder you can write to>"
        ) from None
    return path


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


def provenance(script: str, argv: list[str], cfg) -> dict:
    """What a result file records of the run that made it: the command (``script`` with ``argv``), the code's
    commit, torch's thread count and the whole configuration (a dataclass)."""
    return {
        "command": f"python {script} " + " ".join(argv),
        "commit": git_commit(),
        "torch_threads": torch.get_num_threads(),
        "config": asdict(cfg),
    }


def git_commit(folder: str | Path = ".") -> str | None:
    """The commit checked out where ``folder`` is, with ``+dirty`` if tracked files were changed
    (``None`` outside a git checkout or without git), to record which code made a result."""
    git = ["git", "-C", str(folder)]
    try:
        head, changed = (
            subprocess.run(git + args, capture_output=True, text=True, check=True).stdout.strip()
            for args in (["rev-parse", "HEAD"], ["status", "--porcelain", "--untracked-files=no"])
        )
        return head + ("+dirty" if changed else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def import_ray(what: str):
    """The ``ray`` module, or an ``ImportError`` saying how to install it (``what`` needs it)."""
    try:
        import ray
    except ImportError as error:
        raise ImportError(f'{what} needs Ray: pip install "torchrl_dalir[ray]"') from error
    return ray


@contextmanager
def ray_runtime(what: str, init_config: dict | None = None) -> Iterator:
    """The ``ray`` module, with a runtime: the caller's if Ray is already initialized, else one started with
    ``ray.init(**init_config)`` and shut down on exit (``what`` needs it; see :func:`import_ray`)."""
    ray = import_ray(what)
    started = not ray.is_initialized()
    if started:
        ray.init(**(init_config or {}))
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()
