"""A run directory written tick by tick at a steady rate with the live MCAP on, for tests/test_mcap_live.py:

    python -m tests.live_run_writer OUT N_TICKS RATE_HZ

Three drones of paper_sim, random values (tests.conftest.random_recording) with e_c and e_e derived from
the mission's desired poses (as every flight's are), wall_t the real clock. Prints `follower <pid>` once
the follower runs, `rows <k>` every 100 ticks, then `closed <the follower's report as JSON>`. A file named
`stop` beside OUT ends the run early, at the next multiple of 100 ticks (`stopped <k>` is printed first)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from flightstack.config.rig import resolved_document
from flightstack.recording.files import MISSION_FILE
from flightstack.recording.run_dir import RunWriter
from flightstack.recording.run_reader import resolved_mission
from tests.conftest import random_recording


def main(out: Path, n: int, rate_hz: float) -> int:
    doc = resolved_document("paper_sim")
    ids = [int(d["id"]) for d in doc["drones"]]
    rec = random_recording("none", ids, n, seed=5)
    rec.t[:] = np.arange(n) / rate_hz
    rec.wall_t[:] = time.time() + rec.t
    writer = RunWriter(out, live_mcap=True, block_period_s=0.1)
    writer.write_file(MISSION_FILE, yaml.safe_dump(doc))
    mission, why = resolved_mission(out)
    assert mission is not None, why
    rec.fill_true_errors(np.array([d.desired_pose.pose().as_vector() for d in mission.drones]))
    assert writer.live_mcap is not None
    print(f"follower {writer.live_mcap.proc.pid}", flush=True)
    w = writer.mode("none", ids, n)
    stop = out.parent / "stop"
    t0 = time.monotonic()
    for k in range(n):
        w.append(rec, k + 1)
        if (k + 1) % 100 == 0:
            print(f"rows {k + 1}", flush=True)
            if stop.exists() and k + 1 < n:
                rec.ticks_done = k + 1
                print(f"stopped {k + 1}", flush=True)
                break
        time.sleep(max(0.0, t0 + (k + 1) / rate_hz - time.monotonic()))
    w.close(rec)
    writer.write_metrics({"ticks": rec.ticks_done})
    writer.close()
    print(f"closed {json.dumps(writer.live_mcap.report)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])))
