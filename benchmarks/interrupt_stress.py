"""Ctrl-C at random times in a database run on worker processes: how often it hangs.

Each try starts ``toolkit static database --resolution coarse --plans 300 --workers 1`` in its
own process group (as a terminal does), sends SIGINT to the whole group (the worker included) at
a time drawn uniformly from ``[--earliest, --latest]`` seconds, and waits ``--grace`` seconds for
the command to end. A try that has not ended by then is a hang: its process tree is killed and
the try recorded as such. Per try: the interrupt time, the exit code, the seconds from the
interrupt to the exit, whether the ``interrupted:`` line was printed and whether a traceback
was. Writes ``benchmarks/results/interrupt_stress.csv`` (one row per try) and its sidecar, whose
``extra`` holds the counts.

Usage::

    python benchmarks/interrupt_stress.py                  # 200 tries, about 10 minutes
    python benchmarks/interrupt_stress.py --tries 20 --out /tmp/stress.csv
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/__main__.py", "toolkit/cli/", "toolkit/common/runtime.py", "toolkit/common/training/database.py",
            "toolkit/common/meshes/io.py", "toolkit/static/database.py")

COMMAND = ["static", "database", "--resolution", "coarse", "--plans", "300", "--seed", "1", "--workers", "1",
           "--out", "db.h5"]


def one_try(at_s: float, grace_s: float) -> dict:
    """Run the command, interrupt its process group after ``at_s`` s, wait ``grace_s`` s."""
    with tempfile.TemporaryDirectory(prefix="toolkit-stress-") as tmp:
        # SIGINT's default action, as in a terminal's foreground job (a benchmark started in the
        # background ignores it, and its children would inherit that)
        proc = subprocess.Popen([sys.executable, "-m", "toolkit", *COMMAND], cwd=tmp, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        time.sleep(at_s)
        sent = time.perf_counter()
        ended_before = proc.poll() is not None
        if not ended_before:
            os.killpg(proc.pid, signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=grace_s)
            hung = False
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
            hung = True
        return {"interrupt_s": round(at_s, 3), "ended_before": ended_before, "hung": hung,
                "exit_code": proc.returncode, "exit_after_s": round(time.perf_counter() - sent, 3),
                "interrupted_line": "interrupted:" in err, "traceback": "Traceback" in err,
                "last_line": (err.strip().splitlines() or [""])[-1][:200]}


def main(argv=None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tries", type=int, default=200)
    ap.add_argument("--earliest", type=float, default=0.2, help="s after the start, at the earliest")
    ap.add_argument("--latest", type=float, default=4.0, help="s after the start, at the latest")
    ap.add_argument("--grace", type=float, default=60.0, help="s a command may take to end after the interrupt")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS / "interrupt_stress.csv")
    args = ap.parse_args(argv)

    from tqdm import tqdm

    times = np.random.default_rng(args.seed).uniform(args.earliest, args.latest, args.tries)
    rows = []
    for at in tqdm(times, desc="tries", unit="try"):
        rows.append(one_try(float(at), args.grace))
    df = pd.DataFrame(rows)
    counted = df[~df.ended_before]
    extra = {"tries": int(len(df)), "hung": int(df.hung.sum()),
             "exit_130": int((counted.exit_code == 130).sum()),
             "without_interrupted_line": int((~counted.interrupted_line).sum()),
             "with_traceback": int(counted.traceback.sum()),
             "max_exit_after_s": float(counted.exit_after_s.max()) if len(counted) else None}
    write_result(args.out, df, extra=extra)
    print(extra)
    return df


if __name__ == "__main__":
    main()
