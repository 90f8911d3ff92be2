"""Collection on Ray (issue 19): the rows, reset seeds and labels of a dataset do not depend on the backend or on
the number of workers, also when a collection interrupted on one backend is resumed on the other; sweeps hand their
runs to Ray."""

import runpy
import sys
from pathlib import Path

import pytest
import torch
from conftest import SHORT_REACH, killed_at_source

from torchrl_dalir.config import parse_config
from torchrl_dalir.data import Source, collect
from torchrl_dalir.data.config import PRESETS, CollectionConfig

RAY_CPUS = 2  # a local Ray instance: one CPU per collector actor
SWEEP = Path(__file__).resolve().parents[1] / "examples" / "paper" / "sweep.py"


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance (no dashboard) for the module's tests, shut down afterwards; ``collect`` joins it."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=RAY_CPUS, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_a_collection_resumed_on_two_ray_workers_equals_one_local_worker(tmp_path, local_ray):
    """The first chunk is collected by one local worker, then the collection is killed; it resumes on two Ray
    actors, which interleave their episodes: the dataset equals an uninterrupted one-worker collection row by
    row, and every kept trajectory reset with the same seed."""
    sources = [Source("expert", 1), Source("expert_noisy", 2, noise_scale=0.3)]
    kwargs = dict(seed=6, num_points=32, chunk_size=2, progress=False)
    reference = collect(SHORT_REACH, tmp_path / "reference", sources, num_workers=1, **kwargs)
    with killed_at_source(1), pytest.raises(KeyboardInterrupt):
        collect(SHORT_REACH, tmp_path / "resumed", sources, num_workers=1, **kwargs)
    resumed = collect(SHORT_REACH, tmp_path / "resumed", sources, num_workers=2, backend="ray", **kwargs)
    assert local_ray.is_initialized()  # joined, not shut down: the caller's runtime
    assert (resumed.rows == reference.rows).all()
    assert [s["reset_seeds"] for s in resumed.meta.shards] == [s["reset_seeds"] for s in reference.meta.shards]
    assert torch.equal(resumed.terminal_labels(), reference.terminal_labels())


def test_the_ray_backend_without_ray_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    with pytest.raises(ImportError, match=r'pip install "torchrl_dalir\[ray\]"'):
        collect(SHORT_REACH, tmp_path, [Source("expert", 1)], num_points=32, backend="ray", progress=False)


def test_the_backend_is_a_validated_collection_setting():
    cfg = parse_config(CollectionConfig, ["preset=smoke", "backend=ray", "ray_address=auto", "num_workers=4"], PRESETS)
    kwargs = cfg.collection_kwargs()
    assert (kwargs["backend"], kwargs["ray_init_config"], kwargs["num_workers"]) == ("ray", {"address": "auto"}, 4)
    assert parse_config(CollectionConfig, ["preset=smoke"], PRESETS).collection_kwargs()["ray_init_config"] is None
    with pytest.raises(ValueError, match="backend must be one of"):
        parse_config(CollectionConfig, ["backend=spark"], PRESETS)
    with pytest.raises(ValueError, match="backend must be one of"):
        collect(SHORT_REACH, "unused", [Source("expert", 1)], backend="spark")


def test_more_ray_workers_than_cpus_are_refused_not_left_waiting(tmp_path, local_ray):
    with pytest.raises(ValueError, match=f"the Ray cluster has {RAY_CPUS} CPUs, fewer than num_workers={RAY_CPUS + 1}"):
        collect(
            SHORT_REACH,
            tmp_path,
            [Source("expert", 1)],
            num_points=32,
            num_workers=RAY_CPUS + 1,
            backend="ray",
            progress=False,
        )


def test_the_sweep_hands_one_ray_task_per_run_and_records_what_the_local_launcher_records(
    tmp_path, local_ray, monkeypatch
):
    """Each run's process is stubbed (a main job takes minutes): the Ray launcher runs one task per run and returns
    the local launcher's records, in the same order."""
    sweep = runpy.run_path(str(SWEEP))
    monkeypatch.setitem(
        sweep["run_one"].__globals__, "run_logged", lambda command, log, threads: (0, len(command[2]))
    )  # seconds: len("task=...")
    argv = ["tasks=[reach,door]", "seeds=[0,1]", f"out={tmp_path}"]
    runs = [(task, seed) for seed in (0, 1) for task in ("reach", "door")]
    local = sweep["launch"](parse_config(sweep["Config"], argv), runs)
    on_ray = sweep["launch"](parse_config(sweep["Config"], [*argv, "launcher=ray"]), runs)
    assert on_ray == local and [(r["task"], r["seed"], r["seconds"]) for r in on_ray] == [
        (t, s, len(f"task={t}")) for t, s in runs
    ]
    with pytest.raises(ValueError, match="launcher must be one of"):
        parse_config(sweep["Config"], ["launcher=slurm"])
