"""Plots a person would rather look at than read."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def _save(fig, path: str | Path) -> Path:
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_point_cloud(cloud, path: str | Path, title: str = "", crop_low=None, crop_high=None) -> Path:
    """Saves a 3D scatter (coloured by height) and a top view of one ``[N, 3]`` world-frame cloud."""
    cloud = np.asarray(cloud)
    fig = plt.figure(figsize=(8, 3.6), dpi=80)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    ax.scatter(cloud[:, 0], cloud[:, 1], cloud[:, 2], s=3, c=cloud[:, 2], cmap="viridis")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.view_init(elev=25, azim=-60)
    top = fig.add_subplot(1, 2, 2)
    top.scatter(cloud[:, 0], cloud[:, 1], s=3, c=cloud[:, 2], cmap="viridis")
    top.set_aspect("equal")
    top.set_xlabel("x")
    top.set_ylabel("y")
    top.set_title("top view")
    if crop_low is not None and crop_high is not None:
        for a in (ax,):
            a.set_xlim(crop_low[0], crop_high[0])
            a.set_ylim(crop_low[1], crop_high[1])
            a.set_zlim(crop_low[2], crop_high[2])
        top.set_xlim(crop_low[0], crop_high[0])
        top.set_ylim(crop_low[1], crop_high[1])
    fig.suptitle(f"{title} ({len(np.unique(cloud, axis=0))} distinct of {len(cloud)} points)")
    return _save(fig, path)


def plot_imagination_diagnostics(curves: list[dict], path: str | Path, title: str = "") -> Path:
    """The paper's Fig. 2 for held-out trajectories: (left) scorer output against Monte-Carlo
    targets, (right) scores of imagined against true future latents. ``curves`` holds one dict
    per trajectory with ``label`` (1/0), ``step``, ``target``, ``score``, ``future_step``,
    ``imagined_score`` and ``true_future_score``."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8), dpi=80)
    colors = {1: "tab:blue", 0: "tab:orange"}
    for curve in curves:
        color = colors[int(curve["label"])]
        name = "success" if curve["label"] else "failure"
        left.plot(curve["step"], curve["target"], "--", color=color, alpha=0.8, label=f"MC target ({name})")
        left.plot(curve["step"], curve["score"], "-", color=color, label=f"scorer ({name})")
        right.plot(
            curve["future_step"],
            curve["true_future_score"],
            "--",
            color=color,
            alpha=0.8,
            label=f"true future latent ({name})",
        )
        right.plot(curve["future_step"], curve["imagined_score"], "-", color=color, label=f"imagined latent ({name})")
    left.set_title("task-completion scorer")
    right.set_title("world model: imagined vs true future")
    for ax in (left, right):
        ax.set_xlabel("step")
        ax.set_ylim(-0.05, 1.05)
        ax.legend(fontsize=7)
    left.set_ylabel("completion probability")
    fig.suptitle(title)
    return _save(fig, path)


def plot_success_by_task(
    table: list[dict],
    path: str | Path,
    title: str = "",
    methods: tuple[tuple[str, str], ...] = (("base", "base policy"), ("dalir", "+ DALI-R")),
) -> Path:
    """Grouped bars of each method's success per task (mean over seeds, std as error bars, one dot
    per seed). ``table`` rows: ``task`` and, for every ``(key, label)`` of ``methods``, ``key``
    (a list of per-seed rates), and optionally ``<key>_paper`` (the paper's rate, drawn as a bar-wide
    black line, e.g. Table 1's published numbers; ``None`` where the paper has none)."""
    return plot_metric_by_task(table, path, "success (%)", title, methods, scale=100, ylim=(0, 100))


def plot_metric_by_task(
    table: list[dict],
    path: str | Path,
    ylabel: str,
    title: str = "",
    methods: tuple[tuple[str, str], ...] = (("base", "base policy"), ("dalir", "+ DALI-R")),
    scale: float = 1.0,
    ylim: tuple[float, float] | None = None,
) -> Path:
    """Grouped bars of each method's value of a metric per task, times ``scale`` (mean over seeds, std as
    error bars, one dot per seed, a line at ``<key>_paper`` where a row has it); ``table`` rows as for
    :func:`plot_success_by_task`, with per-seed values.

    Example:
        >>> import tempfile
        >>> table = [{"task": "drill", "with_action": [0.02], "without_action": [0.05], "with_action_paper": 0.03}]
        >>> plot_metric_by_task(table, Path(tempfile.mkdtemp()) / "doc_mse.png", "held-out latent MSE",
        ...                     methods=(("without_action", "WM w/o action"), ("with_action", "WM w/ action"))).name
        'doc_mse.png'
    """
    fig, ax = plt.subplots(figsize=(1.8 + 0.7 * len(methods) * len(table), 3.2), dpi=90)
    x = np.arange(len(table))
    width = 0.8 / len(methods)
    for i, (key, label) in enumerate(methods):
        offset = (i - (len(methods) - 1) / 2) * width
        values = [scale * np.asarray(row[key]) for row in table]
        ax.bar(
            x + offset,
            [v.mean() for v in values],
            width * 0.95,
            yerr=[v.std() for v in values],
            capsize=3,
            label=label,
            alpha=0.8,
        )
        for j, v in enumerate(values):
            ax.scatter(np.full(len(v), x[j] + offset), v, color="k", s=8, zorder=3)
        papers = [
            (x[j] + offset, scale * row[f"{key}_paper"])
            for j, row in enumerate(table)
            if row.get(f"{key}_paper") is not None
        ]
        if papers:
            ax.hlines(
                [y for _, y in papers],
                [c - width * 0.45 for c, _ in papers],
                [c + width * 0.45 for c, _ in papers],
                colors="k",
                linewidth=2,
                zorder=4,
                label="paper" if i == 0 else None,
            )
    ax.set_xticks(x, [row["task"] for row in table])
    ax.set_ylabel(ylabel)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def plot_data_scale(table: list[dict], path: str | Path, title: str = "Mixed-quality data for the world model") -> Path:
    """Held-out latent MSE (left) and DALI-R's success (right) against the number of training
    trajectories, one line per task (paper Table 3b). ``table`` rows: ``task``,
    ``mixed_trajectories`` (a count or ``"all"``, in increasing order per task) and per-seed lists
    ``wm_mse`` and ``success``; means over seeds are drawn, with one dot per seed, and the base
    policy's mean success (``base``, if the rows have it) as a dashed line."""
    fig, axes = plt.subplots(1, 2, figsize=(7.5, 3.2), dpi=90)
    for task in dict.fromkeys(row["task"] for row in table):
        rows = [row for row in table if row["task"] == task]
        x = np.arange(len(rows))
        for ax, key, scale in ((axes[0], "wm_mse", 1), (axes[1], "success", 100)):
            values = [scale * np.asarray(row[key]) for row in rows]
            (line,) = ax.plot(x, [v.mean() for v in values], marker="o", label=task)
            if key == "success" and rows[0].get("base"):
                ax.axhline(
                    100 * np.mean(rows[0]["base"]), color=line.get_color(), linestyle="--", label=f"{task}: base policy"
                )
            for i, v in enumerate(values):
                ax.scatter(np.full(len(v), i), v, color="k", s=8, zorder=3)
            ax.set_xticks(x, [str(row["mixed_trajectories"]) for row in rows])
    axes[0].set_ylabel("held-out latent MSE")
    axes[1].set_ylabel("success (%)")
    axes[1].set_ylim(0, 100)
    for ax in axes:
        ax.set_xlabel("mixed trajectories")
    axes[1].legend(fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def plot_candidate_scaling(
    table: list[dict], path: str | Path, title: str = "Success against the number of candidates"
) -> Path:
    """Success against the number of candidates N (log scale), one line per row of ``table`` (a run
    and a reranking method: ``run``, ``method``, ``candidates`` and ``success``, N = 1 being the base
    policy), as in the paper's Figure 3(b).

    Example:
        >>> import tempfile
        >>> table = [
        ...     {"run": "disassemble dp", "method": "argmax", "candidates": [1, 8, 32], "success": [0.72, 0.8, 0.86]}
        ... ]
        >>> plot_candidate_scaling(table, Path(tempfile.mkdtemp()) / "doc_scaling.png").name
        'doc_scaling.png'
    """
    fig, ax = plt.subplots(figsize=(4.8, 3.2), dpi=90)
    for row in table:
        ax.plot(
            row["candidates"], [100 * s for s in row["success"]], marker="o", label=f"{row['run']}, {row['method']}"
        )
    counts = sorted({n for row in table for n in row["candidates"]})
    ax.set_xscale("log", base=2)
    ax.set_xticks(counts, [str(n) for n in counts])
    ax.set_xlabel("candidates N (1: the base policy)")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def plot_candidate_spread(chunks: dict, path: str | Path, title: str = "") -> Path:
    """Action chunks from one observation, one set per source of variety (``{name: [n, H, A]}``
    tensors or arrays), drawn on the two principal components of all of them together, on equal
    scales (the paper's Figure 3(c) shows re-sampled noise keeping the chunks close and point dropout
    spreading them; ``docs/results/candidate_spread.json`` has what our policies do).

    Example:
        >>> import tempfile, torch
        >>> g = torch.Generator().manual_seed(0)
        >>> chunks = {"noise_only": 0.01 * torch.randn(8, 16, 4, generator=g),
        ...           "dropout": torch.randn(8, 16, 4, generator=g)}
        >>> plot_candidate_spread(chunks, Path(tempfile.mkdtemp()) / "doc_spread.png").name
        'doc_spread.png'
    """
    flat = {name: np.asarray(c, dtype=np.float64).reshape(len(c), -1) for name, c in chunks.items()}
    stacked = np.concatenate(list(flat.values()))
    centre = stacked.mean(0)
    axes = np.linalg.svd(stacked - centre, full_matrices=False)[2][:2]  # the two principal directions
    fig, ax = plt.subplots(figsize=(4.2, 3.6), dpi=90)
    for name, points in flat.items():
        xy = (points - centre) @ axes.T
        ax.scatter(xy[:, 0], xy[:, 1], s=14, alpha=0.7, label=name.replace("_", " "))
    ax.set_aspect("equal", adjustable="datalim")  # distances read the same along both axes
    ax.set_xlabel("first principal component")
    ax.set_ylabel("second principal component")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    return _save(fig, path)


def plot_candidate_outcomes(records: list[dict], path: str | Path, title: str = "") -> Path:
    """Imagined against real outcomes of DALI-R's candidates (records of
    :func:`~torchrl_dalir.branching.candidate_outcomes.candidate_outcomes`): (left) every
    candidate's imagined and real score, each minus its decision's mean, so that only the
    within-decision ordering that reranking uses remains; (middle) the per-decision rank
    correlations; (right, with follow-through records) how often the candidates went on to
    succeed, by the quarter of their imagined score within the decision."""
    from torchrl_dalir.branching.candidate_outcomes import success_by_score_rank

    followed = all("final_success" in r for r in records)
    fig, axes = plt.subplots(1, 3 if followed else 2, figsize=(15 if followed else 10, 3.8), dpi=80)
    left, middle = axes[:2]
    imagined = np.concatenate([np.asarray(r["imagined_score"]) - np.mean(r["imagined_score"]) for r in records])
    real = np.concatenate([np.asarray(r["real_score"]) - np.mean(r["real_score"]) for r in records])
    left.scatter(imagined, real, s=4, alpha=0.4)
    left.axhline(0, color="k", lw=0.5)
    left.axvline(0, color="k", lw=0.5)
    left.set_xlabel("imagined score - decision mean")
    left.set_ylabel("real score - decision mean")
    left.set_title("candidates within a decision")
    correlations = [r["rank_correlation"] for r in records if np.isfinite(r["rank_correlation"])]
    middle.hist(correlations, bins=np.linspace(-1, 1, 21))
    middle.axvline(0, color="k", lw=0.5)
    middle.set_xlabel("Spearman correlation, imagined vs real score")
    middle.set_ylabel("decisions")
    middle.set_title("does imagination order the candidates?")
    if followed:
        right = axes[2]
        scores = ["imagined_score", *(["ensemble_score"] if all("ensemble_score" in r for r in records) else [])]
        width = 0.8 / len(scores)
        for i, score in enumerate(scores):
            right.bar(
                np.arange(4) + i * width, success_by_score_rank(records, score), width, label=score.replace("_", " ")
            )
        right.axhline(
            np.mean([np.mean(r["final_success"]) for r in records]), color="k", lw=0.8, ls="--", label="all candidates"
        )
        right.set_xticks(np.arange(4) + 0.4 - width / 2, ["lowest", "2nd", "3rd", "highest"])
        right.set_xlabel("quarter of the candidate's score within its decision")
        right.set_ylabel("episode success after it")
        right.set_title("do higher scores go on to succeed?")
        right.legend(fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)
