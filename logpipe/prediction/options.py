"""What ``logpipe predict`` is asked (``PredictOptions``) and what it reports (``PredictSummary``, its ``--json``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from logpipe.dataset.sample_filter import SampleFilter
from logpipe.errors import LogpipeError
from logpipe.executor import default_workers

if TYPE_CHECKING:
    from logpipe.prediction.output import ShardWriter


def default_modes(protocol_name: str) -> int:
    """K when ``--modes`` is not given: 20 for pedestrian protocols (ETH/UCY, Social-GAN best-of-20), 6 for the
    vehicle ones (Argoverse K=6, ROS logs at the Argoverse horizon)."""
    return 20 if protocol_name.startswith(("ethucy", "apolloscape")) else 6


PROCESS_MIN_SAMPLES = {True: 250, False: 1500}
"""Samples per core from which a default run forecasts in a process per core, by whether the network has the
environment net: start-up costs ~1.5 s, and on 2,000 samples of the full AV1 model one process on two threads ran
1.33x faster than on one, two processes 1.66x (docs/scaling.md), so processes win from ~8 s of one core's
forecasting: ~150 samples of the full AV1 model (~20 a second on a core), ~1,200 of the ETH network (~160).
"""


OUT_OF_DISTRIBUTION_ACTIONS = ("auto", "warn", "fallback", "refuse")
"""``--out-of-distribution`` (``model.residual.ood`` says what each does)."""


@dataclass(frozen=True)
class PredictOptions:
    """The options of one predict run (the arguments of ``predict_dataset`` after the folders).

    Attributes:
        checkpoint: a checkpoint folder (default: ``default_checkpoint`` for the dataset kind and filter split).
        predictor: a baseline instead (``cv``, ``linear``, ``kalman``, ``cv_sampler``, ``adaptive_cv``).
        modes: K futures per target (default: the K the checkpoint's inference settings were chosen at, else
            ``default_modes``).
        seed: fixes every random draw (noise z, sampler); same seed and settings give the same output.
        noise_scale: standard deviation of the network's noise z (1 = as trained, eq. 21); the spread of the
            K futures. Default: the checkpoint's inference settings (chosen on validation data, ``meta.json``
            ``inference``), else 1. Recorded in ``checkpoint_id`` when not 1.
        constant_velocity_modes: how many of the K futures are the constant-velocity forecast (the network's
            step outputs held at zero). Default: the checkpoint's inference settings, else its training config.
            Recorded in ``checkpoint_id`` when set.
        context_max_neighbours: at most this many of the agents within the checkpoint's ``context_radius_m``
            (the nearest) join each target's context. Default: the checkpoint's inference settings, else all.
            Recorded in ``checkpoint_id`` when set.
        as_trained: ignore the checkpoint's stored inference settings (noise scale 1, its training config).
        sample_filter: which samples (default: all).
        inputs: the roots ROS bags / MCAP files were ingested from (their originals are copied into the output);
            default: the manifest's ``input_roots`` (absolute paths), when ingest records them.
        raster_run: the raster run folder under ``rasters/`` (default: the only one that fits).
        raster_images: add the raster of each sample (PNG image and grid) to the MCAPs when rasters exist.
        write_mcap: write the per-log MCAPs (off: the predictions table only).
        batch_size: samples per forward pass.
        threads: torch intra-op threads (0 = the cores this process may use).
        device: where a checkpoint's network runs: ``auto`` (CUDA when torch can use a GPU, else the CPU), ``cpu``
            or ``cuda`` (autocast there; see ``logpipe.model.training.device``). Baselines run on the CPU whatever it
            says.
        backend: ``local`` (this process) or ``ray``: forecasts on Ray actors (``logpipe.model.ray_predict``;
            the dataset must be on a file system every node shares), outputs written here, the same bytes.
        workers: Ray actors (0: one per GPU of the cluster, else one per CPU); locally, the constant-velocity
            columnar path's parallel shard jobs (0: one per core), and the worker processes a network on the
            CPU forecasts in (``forecast_processes``).
        allow_blank_rasters: let the environment net run on selected samples whose raster is blank (no map, or
            the centre off it); refused by default, since the net would read an empty road as a fact.
        out_of_distribution: for a checkpoint that records its training data's distribution (the residual driving
            model): ``auto`` (flag the targets outside it; on roads it never trained on, mode 0 is the best
            kinematic baseline of its training and the model's modes follow, marked in the ``fallback`` column),
            ``warn`` (flag only), ``fallback`` (every flagged target falls back) or ``refuse`` (an error at the
            first batch with one; shards committed before it stay). ``model.residual.ood`` says why.
    """

    checkpoint: Path | None = None
    predictor: str | None = None
    modes: int | None = None
    seed: int = 0
    noise_scale: float | None = None
    constant_velocity_modes: int | None = None
    context_max_neighbours: int | None = None
    as_trained: bool = False
    sample_filter: SampleFilter | None = None
    inputs: Sequence[Path] = ()
    raster_run: str | None = None
    raster_images: bool = True
    write_mcap: bool = True
    batch_size: int = 64
    threads: int = 0
    device: str = "auto"
    backend: str = "local"
    workers: int = 0
    allow_blank_rasters: bool = False
    out_of_distribution: str = "auto"

    def check(self, modes: int) -> None:
        """Refuse settings no run can use, ``modes`` being the K resolved for the run.

        Raises:
            LogpipeError: K or the batch size below 1, or an unknown backend.
        """
        if modes < 1 or self.batch_size < 1:
            raise LogpipeError(f"--modes and --batch-size must be >= 1, got {modes} and {self.batch_size}")
        if self.backend not in ("local", "ray"):
            raise LogpipeError(f"--backend must be local or ray, got {self.backend!r}")
        if self.out_of_distribution not in OUT_OF_DISTRIBUTION_ACTIONS:
            *others, last = OUT_OF_DISTRIBUTION_ACTIONS
            raise LogpipeError(f"--out-of-distribution must be {', '.join(others)} or {last}, got "
                               f"{self.out_of_distribution!r}")

    def forecast_processes(self, samples: int, *, on_cpu: bool, environment_net: bool) -> int:
        """Local worker processes a network forecasts ``samples`` in (0: this process, on ``threads`` threads);
        none unless it runs ``on_cpu`` (one GPU is not shared between processes).

        ``--workers`` above 1 asks for them. By default (``--workers 0 --threads 0``) one per core once the run
        has ``PROCESS_MIN_SAMPLES`` per core for a network with (or without) the ``environment_net``.
        """
        if self.backend != "local" or not on_cpu:
            return 0
        if self.workers:
            return self.workers if self.workers > 1 else 0
        cores = default_workers()
        enough = samples >= PROCESS_MIN_SAMPLES[environment_net] * cores
        return cores if cores > 1 and not self.threads and enough else 0


@dataclass
class PredictSummary:
    """The run summary; ``to_dict()`` is the ``--json`` output (keys in this order, seconds rounded to ms).

    Counts cover this invocation (shards skipped as already committed are not counted again), except
    ``shards``, ``rows_total``, ``samples_total`` and ``targets_total``: the whole committed run.
    ``already_done``: every shard was committed by an earlier invocation (nothing left to do).
    ``predictor_reason``: why this predictor (the option that named it, or why it is the dataset's default).
    """

    dataset: str
    out: str
    predictor: str
    checkpoint_id: str
    num_modes: int
    seed: int
    checkpoint: str | None
    raster_run: str | None
    inference: dict[str, object] | None
    warnings: list[str]
    protocol: dict[str, Any]
    logs_selected: int
    samples_selected: int
    shards_skipped_done: int = 0
    samples: int = 0
    targets: int = 0
    rows: int = 0
    targets_unobserved: int = 0
    samples_without_targets: int = 0
    targets_out_of_distribution: int = 0
    targets_fallback: int = 0
    mcap_files: int = 0
    original_messages: int = 0
    model_seconds: float = 0.0
    io_seconds: float = 0.0
    io_wait_seconds: float = 0.0
    io_busy_seconds: float = 0.0
    device: str | None = None
    backend: str = "local"
    shards: int = 0
    rows_total: int = 0
    samples_total: int = 0
    targets_total: int = 0
    already_done: bool = False
    predictor_reason: str = ""
    seconds: float = 0.0

    def zeroed(self) -> PredictSummary:
        """A copy with every per-invocation counter at zero (what one shard's work fills, to ``add`` later)."""
        copy = dataclasses.replace(self)
        for name in _COUNTERS:
            setattr(copy, name, 0)
        return copy

    def add(self, other: PredictSummary) -> None:
        """Add ``other``'s per-invocation counters (one shard's, done elsewhere) to this summary's."""
        for name in _COUNTERS:
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def count_writer(self, sink: ShardWriter) -> None:
        """Add a shard writer's counts and times (its busy time overlapped with the model, on its thread)."""
        self.io_seconds += sink.busy_seconds + sink.inline_seconds + sink.files_seconds
        self.io_busy_seconds += sink.busy_seconds
        self.io_wait_seconds += sink.wait_seconds
        self.mcap_files += sink.mcap_files
        self.original_messages += sink.original_messages

    def to_dict(self) -> dict[str, Any]:
        """The ``--json`` summary (``samples_per_s`` over the whole run's wall time)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for key in ("model_seconds", "io_seconds", "io_wait_seconds", "io_busy_seconds", "seconds"):
            out[key] = round(out[key], 3)
        out["samples_per_s"] = round(self.samples / out["seconds"], 1) if out["seconds"] else None
        return out


_COUNTERS = ("samples", "targets", "rows", "targets_unobserved", "samples_without_targets",
             "targets_out_of_distribution", "targets_fallback", "mcap_files", "original_messages", "model_seconds",
             "io_seconds", "io_wait_seconds", "io_busy_seconds")
"""``PredictSummary`` fields that count the work of this invocation, shard by shard."""
