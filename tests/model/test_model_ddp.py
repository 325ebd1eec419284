"""Data-parallel training under torchrun: two processes share each batch and keep identical weights."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

SCRIPT = """
import json, os, sys
from pathlib import Path
from logpipe.model.zhu2020.config import TrainConfig
from logpipe.model.synthetic import make_scenes
from logpipe.model.zhu2020.fit import fit

out = Path(sys.argv[1])
scenes = make_scenes(16, seed=1, min_agents=3, max_agents=6)
config = TrainConfig(steps=4, batch_size=4, eval_every=2, val_max_samples=4, num_modes=3, val_modes=3,
                     num_threads=1)
result = fit(scenes[:12], scenes[12:], config, out / "run", progress=False)
threads = [Path(f"/proc/self/task/{t}/comm").read_text().strip() for t in os.listdir("/proc/self/task")]
summary = {"sha": result.weights_sha256, "processes": result.processes, "steps": result.steps,
           "gloo_threads": sum("gloo" in name for name in threads)}
(out / f"rank{os.environ['RANK']}.json").write_text(json.dumps(summary))
"""


def test_torchrun_two_processes_train_one_model(tmp_path: Path) -> None:
    script = tmp_path / "ddp_train.py"
    script.write_text(SCRIPT)
    torchrun = Path(sys.executable).parent / "torchrun"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [str(torchrun), "--standalone", "--nproc_per_node=2", str(script), str(tmp_path)],
        capture_output=True, text=True, timeout=300, env=env, check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert ranks[0]["processes"] == ranks[1]["processes"] == 2
    assert ranks[0]["steps"] == ranks[1]["steps"] == 4
    assert ranks[0]["sha"] == ranks[1]["sha"]  # gradients were averaged: one model on both processes
    # fit left the process group it joined: gloo threads alive at exit made about one torchrun run in six abort
    assert ranks[0]["gloo_threads"] == ranks[1]["gloo_threads"] == 0
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    assert log[0]["event"] == "start" and log[0]["processes"] == 2
    assert sum(e["event"] == "start" for e in log) == 1  # only process 0 writes the log
    assert (tmp_path / "run" / "best" / "meta.json").is_file()
