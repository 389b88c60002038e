#!/usr/bin/env python3
"""A build in cells on a Ray cluster (docs/cells.md).

Runs `slimkd build SCENE --cells K --plan-only` here (the top of the tree
and the cell files), one Ray task per cell that is not built yet
(`slimkd build-cell CELL -o PART`), then `slimkd stitch`: the same .kd file
as `slimkd build SCENE -o OUT`, byte for byte. Every worker must see the
work directory and the slimkd binary under the same paths as this driver
(shared storage); what crosses the network is Ray's task messages and
the files on that storage: each worker reads one cell file and writes one
part. Rerun after a failure: built parts are kept.

Exit status: 0 success, 1 failure (a step failed; its message names the
cell), 2 usage (including Ray not installed).
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import time


def run_json(cmd):
    """Runs a slimkd command with --json; returns its JSON object or exits 1."""
    p = subprocess.run(cmd + ["--json"], capture_output=True, text=True)
    if p.returncode != 0:
        sys.stderr.write(p.stderr)
        sys.exit(1 if p.returncode == 1 else p.returncode)
    return json.loads(p.stdout)


def build_cell(slimkd, cell, part, threads):
    """One cell: `slimkd build-cell`, on whichever worker Ray picks."""
    p = subprocess.run(
        [slimkd, "build-cell", cell, "-o", part, "-j", str(threads), "--json"],
        capture_output=True,
        text=True,
    )
    if p.returncode != 0:
        raise RuntimeError(f"{cell}: slimkd build-cell failed: {p.stderr.strip()}")
    doc = json.loads(p.stdout)
    doc["host"] = os.uname().nodename
    return doc


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--cells", type=int, required=True, metavar="K")
    ap.add_argument("--cells-dir", required=True, help="work directory on shared storage")
    ap.add_argument("-o", "--output", required=True, help="the .kd file to write")
    ap.add_argument("--reorder", action="store_true")
    ap.add_argument("--slimkd", default=shutil.which("slimkd") or "slimkd",
                    help="the slimkd binary, the same path on every worker")
    ap.add_argument("--address", default=None,
                    help="Ray cluster address (default: start a local Ray instance)")
    ap.add_argument("--threads-per-cell", type=int, default=1,
                    help="threads of each build-cell task (and the CPUs it reserves)")
    ap.add_argument("--num-cpus", type=int, default=None,
                    help="CPUs of a local Ray instance (default: all)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("build_flags", nargs="*",
                    help="build flags after --, e.g. -- --kt 10 (the plan records them)")
    a = ap.parse_args()
    if a.cells < 1 or a.threads_per_cell < 1:
        ap.error("--cells and --threads-per-cell must be at least 1")
    try:
        import ray
    except ImportError:
        print("ray_cells.py: error: Ray is not installed (pip install ray)", file=sys.stderr)
        sys.exit(2)
    slimkd = os.path.abspath(a.slimkd) if os.sep in a.slimkd else a.slimkd
    work = os.path.abspath(a.cells_dir)
    start = time.time()
    plan = run_json([slimkd, "build", a.scene, "--cells", str(a.cells), "--cells-dir", work,
                     "--plan-only", "-q"] + (["--reorder"] if a.reorder else []) + a.build_flags)
    plan_s = time.time() - start
    todo = [c for c in plan["cell_list"] if not c["kept"]]
    if not a.json:
        print(f"planned {len(plan['cell_list'])} cells in {plan_s:.3f} s; "
              f"{len(plan['cell_list']) - len(todo)} parts kept, {len(todo)} to build",
              file=sys.stderr)
    if a.address:
        ray.init(address=a.address, logging_level="WARNING")
    else:
        ray.init(num_cpus=a.num_cpus, include_dashboard=False, logging_level="WARNING")
    task = ray.remote(num_cpus=a.threads_per_cell, max_retries=2)(build_cell)
    cells_start = time.time()
    refs = [task.remote(slimkd, c["cell"], c["part"], a.threads_per_cell) for c in todo]
    results = []
    failed = None
    for r in refs:
        try:
            doc = ray.get(r)
        except Exception as e:  # a task's error names its cell
            failed = failed or e
            continue
        results.append(doc)
        if not a.json:
            print(f"built {doc['cell']} on {doc['host']}: {doc['refs']} references "
                  f"in {doc['build_s']:.3f} s", file=sys.stderr)
    ray.shutdown()
    if failed is not None:
        print(f"ray_cells.py: error: {failed}", file=sys.stderr)
        sys.exit(1)
    cells_s = time.time() - cells_start
    stitch_start = time.time()
    stitched = run_json([slimkd, "stitch", a.scene, "--cells-dir", work, "-o", a.output, "-q"]
                        + (["--reorder"] if a.reorder else []))
    stitch_s = time.time() - stitch_start
    summary = {
        "schema": 1,
        "command": "ray_cells",
        "output": a.output,
        "cells": len(plan["cell_list"]),
        "built": len(results),
        "plan_s": plan_s,
        "cells_s": cells_s,
        "stitch_s": stitch_s,
        "total_s": time.time() - start,
        "cell_build_s": [d["build_s"] for d in results],
        "nodes_total": stitched["nodes_total"],
    }
    if a.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {a.output}: {summary['nodes_total']} nodes; plan {plan_s:.3f} s, "
              f"cells {cells_s:.3f} s ({len(results)} tasks), stitch {stitch_s:.3f} s")


if __name__ == "__main__":
    main()
