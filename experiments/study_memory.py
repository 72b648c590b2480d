"""Time and peak host memory of one calibration study, in one command (for the GPU machine).

    python experiments/study_memory.py --worlds 4096 [--plan default] [--out /tmp/study]

Prints the study's summary, then one JSON line: worlds, wall time s, world-steps/s, peak host
memory GB (``resource.getrusage`` maxrss) and peak device memory GB (``memory_stats``, where the
backend reports it).
"""

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import jax

from jaxcomp.studies.calibration_outputs import study_into, summary
from jaxcomp.studies.calibration_settings import CalibrationSettings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--plan", default="default")
    parser.add_argument("--baseline-sample", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="study-memory.")) / "study"
    settings = CalibrationSettings(
        worlds=args.worlds, plan=args.plan, baseline_sample=args.baseline_sample
    )
    t0 = time.perf_counter()
    report = study_into(out, settings, progress=False).report
    wall = time.perf_counter() - t0
    stats = jax.devices()[0].memory_stats() or {}
    print(summary(report))
    row = {
        "worlds": args.worlds,
        "device": str(jax.devices()[0]),
        "wall_s": wall,
        "world_steps_per_s": report["throughput"]["world_steps_per_s"],
        "peak_host_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "peak_device_gb": stats.get("peak_bytes_in_use", float("nan")) / 2**30,
    }
    print(json.dumps(row))


if __name__ == "__main__":
    main()
