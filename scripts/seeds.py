"""The extra training seeds: which seeds have checkpoints (``make train-* SEED=N`` puts them in
``out/checkpoints/seedN/<kind>/``, outside the package) and were trained with the shipped seed-0 recipe, one seed's
test scores, and the across-seeds table (mean ADE/FDE in metres over the seeds, with ranges)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.dataset.reader import Dataset
from logpipe.model.zhu2020.meta import read_meta
from logpipe.stages.score import score
from logpipe.types import SceneSample
from scripts.forecasts import write_learned, write_predictions
from scripts.locations import CHECKPOINTS, REPO, SEEDS_DIR, SHIPPED_PREFIX, find_checkpoint
from scripts.tables import PAPER, verdict
from scripts.validation import K_BEST, chosen_sampler, tune_sampler


def training_seeds(kind: str, seeds_dir: Path = SEEDS_DIR, shipped: Path = CHECKPOINTS) -> list[int]:
    """The extra training seeds with checkpoints of dataset ``kind``: N of every ``seeds_dir/seedN/kind/``
    (``make train-* SEED=N``) whose checkpoints were all trained with the seed-0 recipe of ``shipped``
    (``stale_seeds``). A seed trained for another dataset only is not one of this dataset's seeds; an absent
    ``seeds_dir`` has none."""
    return sorted(n for n in _seed_folders(kind, seeds_dir) if n not in stale_seeds(kind, seeds_dir, shipped))


def _seed_folders(kind: str, root: Path) -> list[int]:
    """N of every ``root/seedN/`` that holds a ``kind`` folder (none when ``root`` is absent)."""
    return sorted(int(p.name[4:]) for p in root.glob("seed*") if p.name[4:].isdigit() and (p / kind).is_dir())


RECIPE_IGNORES = ("seed", "steps")
"""Config keys that do not make another recipe: the seed, and the step budget (a best checkpoint saved before a run
was continued to a longer schedule with ``--resume`` keeps the budget it was saved under)."""


def _recipe(folder: Path) -> dict[str, Any]:
    """A checkpoint's training config (defaults filled in, model settings its network cannot feel at their defaults:
    ``ModelConfig.effective``) without ``RECIPE_IGNORES``, flattened to dotted keys."""
    trained = read_meta(folder).config
    config = dataclasses.asdict(dataclasses.replace(trained, model=trained.model.effective()))
    flat: dict[str, Any] = {}

    def walk(d: dict[str, Any], prefix: str) -> None:
        for key, value in d.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            elif f"{prefix}{key}" not in RECIPE_IGNORES:
                flat[f"{prefix}{key}"] = value
    walk(config, "")
    return flat


def stale_seeds(kind: str, seeds_dir: Path = SEEDS_DIR, shipped: Path = CHECKPOINTS) -> dict[int, list[str]]:
    """Seed folders of ``kind`` in ``seeds_dir`` with a checkpoint trained by another recipe than the seed-0
    checkpoint at the same place in ``shipped`` (an older config): seed -> ``"<folder>: <differing keys>"`` lines.
    Such a seed is no repeat of the shipped runs, so the across-seeds tables leave it out until it is retrained."""
    out: dict[int, list[str]] = {}
    for n in _seed_folders(kind, seeds_dir):
        for meta in sorted((seeds_dir / f"seed{n}" / kind).rglob("meta.json")):
            rel = meta.parent.relative_to(seeds_dir / f"seed{n}")
            seed0 = shipped / rel / "meta.json"
            if not seed0.is_file():
                continue
            mine, theirs = _recipe(meta.parent), _recipe(seed0.parent)
            differ = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
            if differ:
                out.setdefault(n, []).append(f"{rel.as_posix()}: {', '.join(differ)}")
    return out


def stale_summary(lines: Sequence[str]) -> str:
    """``stale_seeds`` lines grouped by the config keys that differ, so 15 checkpoints off by one key read as one
    phrase: "`model.mode_gate` in 15 checkpoints"; groups of up to 3 name their folders."""
    groups: dict[str, list[str]] = {}
    for line in lines:
        folder, keys = line.split(": ", 1)
        groups.setdefault(keys, []).append(folder)
    return "; ".join(f"`{keys}` in {len(folders)} checkpoint{'s' if len(folders) > 1 else ''}"
                     + (f" ({', '.join(folders)})" if len(folders) <= 3 else "")
                     for keys, folders in groups.items())


def seed_template(template: str, seed: int, seeds_dir: Path = SEEDS_DIR) -> str:
    """Where ``make train-* SEED=seed`` puts (in ``seeds_dir``) the checkpoint that the shipped ``template`` names for
    seed 0; a template outside the package stays as given."""
    if not template.startswith(SHIPPED_PREFIX):
        return template
    return f"{seeds_dir.resolve().as_posix()}/seed{seed}/{template.removeprefix(SHIPPED_PREFIX)}"


def seed_run(  # noqa: PLR0913  one seed's rerun of the caller's loaded data and settings
    seed: int, templates: dict[str, str], learned: dict[str, tuple[str, int]], scene: str, ds: Dataset,
    val: Sequence[SceneSample], test: Sequence[SceneSample], split: str, min_agents: int,
    work: Path, train: Sequence[SceneSample] | None = None, seeds_dir: Path = SEEDS_DIR,
) -> dict[str, Any]:
    """One extra seed's test ADE/FDE: the sampler with sampling seed ``seed`` (its noise chosen on ``val`` again) and
    each learned method whose ``seed`` checkpoint exists in ``seeds_dir``, trained with ``train.seed = seed`` and
    sampled with it (its inference settings chosen on ``val``); scored like the main table, without plots. Returns
    method -> (K, ADE, FDE)."""
    pred_len = ds.protocol.pred_len
    choice, _ = tune_sampler(val, pred_len, K_BEST, seed)
    files = [write_predictions(chosen_sampler(choice, pred_len), test, K_BEST, seed, pred_len,
                               f"cv_sampler {choice} seed {seed}", work / "cv_sampler.parquet", "cv_sampler")]
    ks = {"cv_sampler": K_BEST}
    for method, (_, k) in learned.items():
        ckpt = find_checkpoint(seed_template(templates[method], seed, seeds_dir), scene)
        if ckpt is not None:
            files += write_learned(ckpt, ds.kind, val, test, k, seed, pred_len, work, method, train=train,
                                   as_specified=method == PAPER)[0]
            ks[method] = k
    report = score(files, ds.root, work / "report", split=split, min_agents=min_agents, plots=False,
                   title=f"{split}, training seed {seed}")
    return {m: (k, report["methods"][m]["overall"][f"k{k}"]["ade"], report["methods"][m]["overall"][f"k{k}"]["fde"])
            for m, k in ks.items()}


SEED_METHODS = (("CV sampler, best-of-20", "cv_sampler", K_BEST), ("LSTM (K=1)", "lstm", 1),
                ("Noise-LSTM, best-of-20", "noise_lstm", K_BEST),
                ("Our method (zhu2020), best-of-20", "zhu2020", K_BEST))
"""Rows of the across-seeds tables: (label, method, K)."""


def seed_values(main: dict[str, Any], extra: dict[int, dict[str, Any]], method: str,
                k: int) -> list[tuple[float, float]]:
    """(ADE, FDE) of ``method`` at ``k`` per training seed: seed 0 from the main report's ``methods`` block, then
    every extra seed that ran it."""
    block = main.get(method, {}).get("overall", {}).get(f"k{k}")
    values = [(block["ade"], block["fde"])] if block else []
    return values + [(r[method][1], r[method][2]) for _, r in sorted(extra.items()) if method in r]


def across_seeds_table(columns: Sequence[str], cells: dict[str, dict[str, list[tuple[float, float]]]],
                       with_avg: bool) -> list[str]:
    """Markdown: per method (``SEED_METHODS``) and column, the mean ADE/FDE over seeds with its min-max range and
    seed count, then whether the paper's method's means beat each baseline's (both lower)."""
    head = "| method | " + " | ".join(c.upper() for c in columns) + (" | AVG |" if with_avg else " |")
    lines = [head, "|---|" + "---|" * (len(columns) + with_avg)]
    means: dict[str, list[tuple[float, float]]] = {}
    for label, method, _ in SEED_METHODS:
        per = [cells[c].get(method, []) for c in columns]
        if not all(per):
            continue
        n = {len(v) for v in per}
        means[method] = [tuple(np.mean(v, axis=0)) for v in per]
        row = [f"{a:.3f}/{f:.3f} ({min(x[0] for x in v):.3f}-{max(x[0] for x in v):.3f} / "
               f"{min(x[1] for x in v):.3f}-{max(x[1] for x in v):.3f})" for (a, f), v in zip(means[method], per,
                                                                                        strict=True)]
        if with_avg:
            row.append("{:.3f}/{:.3f}".format(*np.mean(means[method], axis=0)))
        lines.append(f"| {label} (seeds: {'/'.join(map(str, sorted(n)))}) | " + " | ".join(row) + " |")
    ours = means.get("zhu2020")
    if ours is None:
        return [*lines, "", "The paper's method has no seed runs here."]
    lines += ["", "Standing of the paper's method on these means (ADE and FDE both lower = beaten):", "",
              "| baseline | " + " | ".join(c.upper() for c in columns) + (" | AVG |" if with_avg else " |"),
              "|---|" + "---|" * (len(columns) + with_avg)]
    for label, method, _ in SEED_METHODS[:-1]:
        if method not in means:
            continue
        pairs = list(zip(ours, means[method], strict=True))
        if with_avg:
            pairs.append((tuple(np.mean(ours, axis=0)), tuple(np.mean(means[method], axis=0))))
        lines.append(f"| {label} | " + " | ".join(verdict(m, o) for m, o in pairs) + " |")
    return lines


def shown(folder: Path) -> str:
    """``folder`` as the results files name it: relative to the repository when inside it."""
    folder = folder.resolve()
    return folder.relative_to(REPO).as_posix() if folder.is_relative_to(REPO) else str(folder)


def no_seeds_note(seeds_dir: Path, kind: str) -> str:
    """What a results file says when ``seeds_dir`` holds no extra training seed of ``kind``."""
    return (f"No checkpoints of extra training seeds in `{shown(seeds_dir)}/seedN/{kind}/` (`make train-{kind} "
            "SEED=N` puts them there; `--seeds-dir` reads another folder), so only training seed 0 is reported.")
