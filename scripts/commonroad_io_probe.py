"""Parse CommonRoad files with the official ``commonroad-io`` reader; one JSON line on stdout (file → result).

Runs in a venv of its own (``commonroad-io`` pins ``protobuf==3.20.2``; logpipe needs protobuf >= 4.25);
``scripts/commonroad_readers.py`` calls it. It touches every state, as logpipe's reader does.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
import warnings
from typing import Any


def main(paths: list[str]) -> None:
    from commonroad.common.file_reader import CommonRoadFileReader  # only in the probe's own venv

    warnings.filterwarnings("ignore")
    out: dict[str, dict[str, Any]] = {}
    for path in paths:
        started = time.perf_counter()
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # it prints a line per deprecated intersection tag
                scenario, _ = CommonRoadFileReader(path).open()
            states = sum(len(o.prediction.trajectory.state_list) + 1 for o in scenario.dynamic_obstacles
                         if o.prediction is not None)
            result: dict[str, Any] = {"ok": True, "states": states}
        except Exception as err:  # what the reader raises on a damaged file is the measurement
            result = {"ok": False, "error": f"{type(err).__name__}: {str(err)[:200]}"}
        result["seconds"] = time.perf_counter() - started
        out[path] = result
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1:])
