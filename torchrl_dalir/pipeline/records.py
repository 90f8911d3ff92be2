"""Run records: the outcome of one main-job run in a small JSON file that can be committed.

A run's folder (datasets, checkpoints, ``results.json`` with every episode's details) is large
and lives outside the repository; a run record keeps what the result tables need: the command
that made the run, every method's success on each test episode (``"0110..."``), the selection
rule it used, its calibration on validation episodes and, for runs that logged them, each stage's
wall time (the attempt that finished it) and the job's peak memory. Records written by different sessions
on different machines add up: ``examples/paper/summarize_results.py records=[docs/results/runs]``
builds the tables from them, so seeds can be added one run at a time.

A record whose per-episode outcomes were not kept (runs summarised before records existed)
gives, per method, the discordant counts against the base policy (``base_only``, ``method_only``)
instead; the sign tests need nothing more.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.evaluation.compare import METHODS, paired_sign_test
from torchrl_dalir.pipeline.config import PRESETS, STAGE_LOG, PipelineConfig
from torchrl_dalir.utils import atomic_write

RECORD_VERSION = 1
PAPER = "paper"  # the variant of a run with the paper's world model and data
SHORT = {name: short for short, name in METHODS.items()}  # "base policy" -> "base", ...
# the stages' settings that the main job derives from its own task, seed, device, logging and folder,
# and its own settings that do not change a run's results: not part of the command (runs before
# wandb became opt-in logged to offline wandb runs: policy_training.wandb=true)
_DERIVED = {"out", "data", "mixed_name", "policy_checkpoint", "task", "seed", "policy", "device", "wandb"}
_NOT_RESULTS = {"out", "preset", "task", "seed", "policy", "redo", "until", "wandb"}
TIMING_KEYS = ("stage_seconds", "peak_memory_gib", "workers_peak_memory_gib")  # from the run's stage log
# settings whose default changed after they were added: the value a run that predates them ran at
_ADDED_AS = {"calibration_grid": "all"}


def variant_label(run_name: str, policy: str, seed: int) -> str:
    """The world-model variant of a run folder ``<policy>_seed<seed><variant>``, with the seed
    taken out of the datasets it names (``fm_seed0_frozen+explore_fm_seed0`` -> ``frozen+explore``),
    so that the seeds of one variant group together; ``paper`` for none."""
    own = f"_{policy}_seed{seed}"
    return run_name.removeprefix(own[1:]).replace(own, "").lstrip("_") or PAPER


def config_variant(cfg: PipelineConfig) -> str:
    """The world-model variant (:func:`variant_label`) of the runs a main-job configuration makes."""
    return variant_label(cfg.run_name(), cfg.policy, cfg.seed)


DEFAULT_VARIANT = config_variant(parse_config(PipelineConfig, [], PRESETS))  # the cpu preset's: frozen+explore


def outcome_string(records: list[dict]) -> str:
    """Episode records (each with ``success``) as one string of outcomes, ``"0110..."`` in episode order."""
    return "".join("1" if r["success"] else "0" for r in records)


def successes(outcomes: str) -> list[bool]:
    """The per-episode successes of an :func:`outcome_string` (``"0110"`` -> ``[False, True, True, False]``)."""
    return [c == "1" for c in outcomes]


def command(config: dict) -> str:
    """The main-job command line of a run of ``config`` (a ``results.json``'s ``config``): its
    task, seed, policy and preset, and every setting that differs from the preset. (It sets what
    the run set: ``precision=auto`` still chooses for the machine it runs on.)"""
    head = {key: config[key] for key in ("task", "seed", "policy", "preset")}
    default = config_dict(
        parse_config(PipelineConfig, [f"{k}={v}" for k, v in {**head, "out": config["out"]}.items()], PRESETS)
    )
    default = json.loads(json.dumps(default))  # as the run's results.json holds it (tuples become lists)
    base = _flatten(default)
    # a setting that the run's code did not have yet ran at the value it was added with
    own = {**_flatten(json.loads(json.dumps(config_dict(PipelineConfig())))), **_ADDED_AS, **_flatten(config)}
    explore = f"explore_{config['policy']}_seed{config['seed']}"
    for flat in (own, base):  # the exploration data joins the world model's data by itself
        if flat.get("exploration_rollouts"):
            flat["world_model.extra_data"] = [
                name for name in flat.get("world_model.extra_data", []) if name != explore
            ]
    changed = [
        f"{key}={_cli(value)}"
        for key, value in own.items()
        if key in base
        and value != base[key]  # (a setting that no longer exists is left out)
        and (key.rsplit(".", 1)[-1] not in _DERIVED if "." in key else key not in _NOT_RESULTS)
    ]
    return " ".join(["python examples/train_dp3_wm.py", *(f"{k}={v}" for k, v in head.items()), *changed])


def run_record(
    result: dict, run: str, calibration: dict | None = None, commit: str | None = None, stages: dict | None = None
) -> dict:
    """The record of one main-job run from its ``results.json`` (``result``), its folder name
    ``run`` and its ``calibration.json`` (if it was calibrated). ``commit`` names the code that
    made the run when ``result`` does not (results written before they named it). ``stages``:
    the run's lines of the stage log by stage (:func:`stage_log`), kept as each stage's wall time
    and the job's peak memory."""
    config = result["config"]
    if (
        calibration and calibration.get("alpha") is not None
    ):  # runs from before the setting calibrated at their own alpha
        config = {**config, "calibration_alpha": calibration["alpha"]}
    methods = {}
    for name, row in result["success"].items():
        outcomes = outcome_string(row["records"])
        methods[SHORT[name]] = {
            "success_rate": row["success_rate"],
            "outcomes": outcomes,
            **({"selection": row["selection"]} if "selection" in row else {}),
            "seconds": row.get("seconds"),
        }
    record = {
        "version": RECORD_VERSION,
        "task": config["task"],
        "policy": config["policy"],
        "seed": config["seed"],
        "variant": variant_label(run, config["policy"], config["seed"]),
        "run": run,
        "eval_seed": config["eval_seed"],
        "episodes": config["eval_episodes"],
        "num_candidates": config["num_candidates"],
        "command": command(config),
        "commit": result.get("commit") or commit,
        "methods": methods,
    }
    if calibration and calibration.get("design") == "failures":  # calibrate_on_failures: a screen, then a confirmation
        record["validation"] = {
            "design": "failures",
            "episodes": calibration["episodes"],
            "seed": calibration["seed"],
            "alpha": calibration["alpha"],
            "base": round(calibration["base_success_rate"], 4),
            "failed": len(calibration["failed"]),
            "chosen": calibration["chosen"],
            "entries": {
                e["name"]: {"wins": e["wins"], "losses": e["losses"], "estimated_gain": round(e["estimated_gain"], 4)}
                for e in calibration["entries"]
            },
        }
    elif calibration and calibration.get("entries"):
        record["validation"] = {
            "episodes": calibration["episodes"],
            "seed": calibration["seed"],
            "alpha": calibration.get("alpha"),
            "base": round(calibration["base_success_rate"], 4),
            "chosen": calibration["chosen"],
            "entries": {
                e["name"]: {
                    "success_rate": round(e["success_rate"], 4),
                    "base_only": e["vs_base"]["base_only"],
                    "method_only": e["vs_base"]["dalir_only"],
                }
                for e in calibration["entries"]
            },
        }
    confirmation = (calibration or {}).get("confirmation")
    if confirmation and "validation" in record:  # the chosen entry re-run on fresh validation episodes
        record["validation"]["confirmation"] = {
            "episodes": confirmation["episodes"],
            "seed": confirmation["seed"],
            "entry": confirmation["entry"],
            "base": round(confirmation["base_success_rate"], 4),
            "success_rate": round(confirmation["success_rate"], 4),
            "base_only": confirmation["vs_base"]["base_only"],
            "method_only": confirmation["vs_base"]["dalir_only"],
            "confirmed": confirmation["confirmed"],
        }
    if stages:
        record["stage_seconds"] = {name: line["seconds"] for name, line in stages.items()}
        for key in TIMING_KEYS[1:]:  # the job's high-water marks: this process, its largest collector worker
            memory = [line[key] for line in stages.values() if line.get(key) is not None]
            record[key] = max(memory) if memory else None
    return record


def _with_timings(record: dict, other: dict) -> dict:
    """``record``, given ``other``'s stage timings where it has none (the same run summarised from a
    folder that no longer holds its stage log)."""
    if "stage_seconds" in record or "stage_seconds" not in other:
        return record
    return {**record, **{key: other[key] for key in TIMING_KEYS if key in other}}


def stage_log(root: str | Path) -> dict[str, dict[str, dict]]:
    """The main job's stage logs under ``root`` (``stages/<task>/<run>.jsonl``, a line as each stage
    finishes) as ``{"<task>/<run>": {stage: its last line}}``: a stage redone later counts once, with
    its last time. A line cut short by a crash is skipped."""
    runs = {}
    for path in sorted(Path(root).glob(f"{STAGE_LOG}/*/*.jsonl")):
        lines = runs.setdefault(f"{path.parent.name}/{path.name.removesuffix('.jsonl')}", {})
        for text in path.read_text().splitlines():
            try:
                line = json.loads(text)
            except json.JSONDecodeError:
                continue
            lines[line["stage"]] = line
    return runs


def discordant(record: dict, method: str, against: str = "base") -> tuple[int, int] | None:
    """The test episodes that only ``against`` / only ``method`` solved in ``record`` (by default
    against the base policy, whose counts every record keeps); ``None`` for two other methods
    whose per-episode outcomes the record does not both keep."""
    row, other = record["methods"][method], record["methods"][against]
    if "outcomes" in row and "outcomes" in other:
        test = paired_sign_test(successes(other["outcomes"]), successes(row["outcomes"]))
        return test["base_only"], test["dalir_only"]
    return (row["base_only"], row["method_only"]) if against == "base" else None


def check_record(record: dict, where: str = "a run record") -> None:
    """Refuses a record that cannot be summarised: another version, no base policy, a method with
    neither its outcomes nor its discordant counts, outcomes of another number of episodes, or
    counts that do not add up to the success rates."""
    if record.get("version") != RECORD_VERSION:
        raise ValueError(f"{where} is not a run record of version {RECORD_VERSION}")
    methods, episodes = record["methods"], record["episodes"]
    if "base" not in methods:
        raise ValueError(f"{where} has no base policy to compare with")
    for name, row in methods.items():
        if "outcomes" in row:
            if len(row["outcomes"]) != episodes or set(row["outcomes"]) - {"0", "1"}:
                raise ValueError(f"{where}: {name}'s outcomes must be {episodes} characters 0 or 1")
            if abs(row["outcomes"].count("1") / episodes - row["success_rate"]) > 1e-6:
                raise ValueError(f"{where}: {name}'s outcomes do not give its success rate {row['success_rate']}")
        elif name != "base":
            if not {"base_only", "method_only"} <= set(row):
                raise ValueError(
                    f"{where}: {name} has neither its outcomes nor its discordant counts (base_only, method_only)"
                )
            if (
                abs(
                    (row["method_only"] - row["base_only"]) / episodes
                    - (row["success_rate"] - methods["base"]["success_rate"])
                )
                > 1e-6
            ):
                raise ValueError(f"{where}: {name}'s discordant counts do not add up to the success rates")


def records_from_runs(root: str | Path, commit: str | None = None) -> list[dict]:
    """A record of every main-job run under ``root`` (``<root>/results/<task>/<run>/results.json``
    and its calibration); runs of some methods only (Table 3's arg-max-only variants) are left out.
    ``commit``: see :func:`run_record`."""
    root = Path(root)
    records, stages = [], stage_log(root)
    for path in sorted(root.glob("results/*/*/results.json")):
        result = json.loads(path.read_text())
        if not {METHODS["base"], METHODS["dalir"]} <= set(result["success"]):
            continue
        task, run = path.parent.parent.name, path.parent.name
        calibration = root / "calibration" / task / run / "calibration.json"
        records.append(
            run_record(
                result,
                run,
                json.loads(calibration.read_text()) if calibration.exists() else None,
                commit,
                stages.get(f"{task}/{run}"),
            )
        )
    return records


def load_records(folders: list[str | Path]) -> list[dict]:
    """Every record (``*.json``) under ``folders``, each checked by :func:`check_record`."""
    records = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("*.json")):
            record = json.loads(path.read_text())
            check_record(record, str(path))
            records.append(record)
    return records


def record_path(folder: str | Path, record: dict) -> Path:
    return Path(folder) / record["variant"] / record["task"] / f"{record['policy']}_seed{record['seed']}.json"


def save_records(records: list[dict], folder: str | Path) -> list[Path]:
    """Writes each record to ``<folder>/<variant>/<task>/<policy>_seed<seed>.json``. A record
    already there is only replaced by one of the same run (the same outcomes of every method):
    two runs of one seed are refused, before anything is written."""
    paths = [record_path(folder, record) for record in records]
    saved = {path: json.loads(path.read_text()) for path in paths if path.exists()}
    for path, record in zip(paths, records):
        check_record(record, f"the record for {path}")
        if path in saved and saved[path]["methods"] != record["methods"]:
            raise ValueError(
                f"{path} holds another run of {record['task']} {record['policy']} seed {record['seed']}: "
                "move it away to replace it"
            )
    for path, record in zip(paths, records):
        if path in saved:  # the same run: keep the timings it was saved with
            record = _with_timings(record, saved[path])
        atomic_write(path, json.dumps(record, indent=1) + "\n")
    return paths


def merge_records(*sources: list[dict]) -> list[dict]:
    """The records of every source, one per (task, policy, variant, seed); the first source's wins,
    with a warning where another source holds a different run of the same seed."""
    merged = {}
    for records in sources:
        for record in records:
            key = (record["task"], record["policy"], record["variant"], record["seed"])
            kept = merged.setdefault(key, record)
            if kept["methods"] == record["methods"]:
                merged[key] = _with_timings(kept, record)
            else:
                warnings.warn(
                    f"two different runs of {' '.join(map(str, key))}: "
                    f"the one of {kept['run']} (commit {kept['commit']}) is used",
                    stacklevel=2,
                )
    return list(merged.values())


def _flatten(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _cli(value) -> str:
    if isinstance(value, list):
        return "[" + ",".join(map(_cli, value)) + "]"
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)
