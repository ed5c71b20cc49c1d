"""Benchmark: CPU time of ``calibrate()`` per component, optionally beside another checkout's code.

Run: OMP_NUM_THREADS=1 .venv/bin/python benchmarks/compensation_timing.py [--seeds 2] [--passes 2]
     [--against /path/to/other/checkout]

Draws hard campaigns (the ``hard`` profile and ``period-3``: a 3.0-step ripple beside the slower
terms, issue 25) of seeds 0..N-1 for every component with this checkout's ``hard_campaign``, saves
their calibration arrays, and times ``calibrate(data, seed=seed)`` on each (``time.process_time``,
one core; one warm-up call first) in a fresh process per pass. With ``--against``, every pass also
times the other checkout's ``instrument.compensation`` on the same arrays, right after this one's,
so both see the same machine load (a temporary ``git worktree add /tmp/other main`` serves). The
load average is printed before each run. Target (issue 25): <= 2 s per component on one core.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]

WORKER = """
import glob, json, os, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
import instrument.compensation as compensation
from instrument.compensation import CalibrationData, calibrate
assert compensation.__file__.startswith(sys.argv[1]), compensation.__file__
files = sorted(glob.glob(os.path.join(sys.argv[2], "*.npz")))
def load(f):
    z = np.load(f)
    return CalibrationData(str(z["component"]), z["measured"], z["reference"], z["group"], z["point"]), int(z["seed"])
calibrate(*[load(files[0])[0]], seed=0)
out = {}
for f in files:
    data, seed = load(f)
    started = time.process_time()
    calibrate(data, seed=seed)
    out[os.path.basename(f)[:-4]] = time.process_time() - started
print(json.dumps(out))
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seeds", type=int, default=2, help="campaigns per profile and component (seeds 0..N-1)")
    parser.add_argument("--passes", type=int, default=2, help="times every code is run over all campaigns")
    parser.add_argument("--against", type=Path, help="another checkout whose calibrate() to time on the same data")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from instrument.compensation import COMPONENTS, hard_campaign

    profiles = {"hard": {}, "period-3": {"profile": "short-ripple", "ripple_period": 3.0}}
    roots = [ROOT] + ([args.against.resolve()] if args.against else [])
    with tempfile.TemporaryDirectory() as folder:
        for name, keywords in profiles.items():
            for seed in range(args.seeds):
                for component in COMPONENTS:
                    d = hard_campaign(seed, component, **keywords).calibration
                    np.savez(Path(folder) / f"{name}-{seed}-{component}.npz", measured=d.measured,
                             reference=d.reference, group=d.group, point=d.point, component=component, seed=seed)
        print(f"calibrate() CPU time per component, {len(profiles) * args.seeds * len(COMPONENTS)} calibrations "
              "per run (hard and period-3 campaigns), one core")
        for run in range(1, args.passes + 1):
            for root in roots:
                load = " ".join(f"{v:.1f}" for v in os.getloadavg())
                text = subprocess.run([sys.executable, "-c", WORKER, str(root), folder], check=True,
                                      capture_output=True, text=True).stdout
                times = json.loads(text)
                cells = []
                for name in profiles:
                    t = np.array([v for k, v in times.items() if k.startswith(name + "-")])
                    cells.append(f"{name} {t.mean():.2f} / {t.max():.2f}")
                every = np.array(list(times.values()))
                print(f"pass {run} {str(root):40s} load {load}: mean / max s: " + ", ".join(cells)
                      + f"; all {every.mean():.2f} / {every.max():.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
