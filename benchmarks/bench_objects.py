"""Microseconds per object of graphopt's per-object API (``add_vertex``/``add_edge``, g2o's way
of building), before and after the buffered objects, in the same run.

Workload (issue 23): a 20 + 30-keyframe local BA — 50 ``VertexSE3Expmap`` (30 fixed), 5,000
marginalised ``VertexPointXYZ``, 25,000 ``EdgeSE3ProjectXYZ`` with an information matrix per
edge (``I / σ²`` of one of 8 pyramid levels, as ORB-SLAM sets them) and a Huber kernel — built
one object at a time. Timed per object:

* ``vertex``: construct + ``add_vertex``; ``add_vertex``: the call alone (objects made before);
* ``edge``: construct + ``set_*`` + ``add_edge``; ``add_edge``: the call alone;
* ``flush``: taking the buffered objects into the arrays (the new code's bulk checks; the old
  code did that work inside ``add_*``), per edge;
* ``build``: everything up to the arrays, per edge (vertices + edges + flush) / 25,000;
* ``estimate``: reading ``v.estimate`` back, per vertex;
* ``bulk``: ``add_vertices`` + ``add_edges`` of the same graph (ms).

"before" is the code at ``--ref`` (default ``main``), extracted with ``git archive`` and
imported in a subprocess; "after" is this checkout. The two alternate, one process per build,
medians of ``--repeats``; one thread each (OMP/OpenBLAS = 1). The old code's kernel lookup is
linear in the kernels of a group, so a kernel object per edge (ORB-SLAM's way) would be
quadratic there: the shared-kernel program is compared, and the per-edge one is timed after only.

Usage::

    .venv/bin/python -P benchmarks/bench_objects.py [--repeats 5] [--ref main]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tarfile  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _import_from(src: Path) -> None:
    """Make ``import graphopt`` (and its ``types``/``apps`` packages) load from ``src``."""
    roots = {"graphopt": src / "graphopt", "graphopt.types": src / "types",
             "graphopt.apps": src / "apps"}

    class Finder:
        @classmethod
        def find_spec(cls, name: str, path: Any = None, target: Any = None) -> Any:
            if name in roots:
                return importlib.util.spec_from_file_location(
                    name, roots[name] / "__init__.py",
                    submodule_search_locations=[str(roots[name])])
            return None

    sys.meta_path.insert(0, Finder)  # type: ignore[arg-type]


def worker(per_edge_kernel: bool) -> dict[str, float]:
    """One build of the workload, one object at a time; µs per object (ms for ``bulk``)."""
    import numpy as np

    from graphopt import RobustKernelHuber, SparseOptimizer
    from graphopt.lie import make_transform, so3_exp
    from graphopt.types import (
        CameraParameters,
        EdgeSE3ProjectXYZ,
        VertexPointXYZ,
        VertexSE3Expmap,
    )

    rng = np.random.default_rng(0)
    nk, nfree, npts, m = 50, 20, 5000, 25000
    T = make_transform(so3_exp(rng.normal(0, 0.02, (nk, 3))), rng.normal(0, 1, (nk, 3)))
    X = rng.normal(0, 1, (npts, 3)) + [0, 0, 6]
    ids = np.column_stack([rng.integers(0, nk, m), nk + rng.integers(0, npts, m)])
    meas = rng.uniform(0, 640, (m, 2))
    inv_sigma2 = 1.0 / 1.2 ** (2 * np.arange(8))
    octave = rng.integers(0, 8, m)
    cam = CameraParameters(500.0, 500.0, 320.0, 240.0)
    delta = float(np.sqrt(5.991))
    shared = RobustKernelHuber(delta)
    out: dict[str, float] = {}
    opt = SparseOptimizer()
    t0 = time.perf_counter()
    vs = []
    for i in range(nk):
        v = VertexSE3Expmap(i, T[i], fixed=i >= nfree)
        opt.add_vertex(v)
        vs.append(v)
    for j in range(npts):
        v = VertexPointXYZ(nk + j, X[j], marginalized=True)
        opt.add_vertex(v)
        vs.append(v)
    t1 = time.perf_counter()
    for a, b, z, o in zip(ids[:, 0].tolist(), ids[:, 1].tolist(), meas, octave.tolist(),
                          strict=True):
        e = EdgeSE3ProjectXYZ(params=cam)
        e.set_vertex(0, vs[a])
        e.set_vertex(1, vs[b])
        e.set_measurement(z)
        e.set_information(np.eye(2) * inv_sigma2[o])
        e.set_robust_kernel(RobustKernelHuber(delta) if per_edge_kernel else shared)
        opt.add_edge(e)
    t2 = time.perf_counter()
    if hasattr(opt.graph, "flush"):
        opt.graph.flush()
    t3 = time.perf_counter()
    for v in vs:
        v.estimate  # noqa: B018
    t4 = time.perf_counter()
    nv = nk + npts
    out.update(vertex=(t1 - t0) / nv * 1e6, edge=(t2 - t1) / m * 1e6, flush=(t3 - t2) / m * 1e6,
               build=(t3 - t0) / m * 1e6, estimate=(t4 - t3) / nv * 1e6)
    # The calls alone: objects made first.
    opt = SparseOptimizer()
    vs = [VertexSE3Expmap(i, T[i], fixed=i >= nfree) for i in range(nk)]
    vs += [VertexPointXYZ(nk + j, X[j], marginalized=True) for j in range(npts)]
    es = []
    for a, b, z, o in zip(ids[:, 0].tolist(), ids[:, 1].tolist(), meas, octave.tolist(),
                          strict=True):
        es.append(EdgeSE3ProjectXYZ([vs[a], vs[b]], z, np.eye(2) * inv_sigma2[o],
                                    RobustKernelHuber(delta) if per_edge_kernel else shared,
                                    params=cam))
    t0 = time.perf_counter()
    for v in vs:
        opt.add_vertex(v)
    t1 = time.perf_counter()
    for e in es:
        opt.add_edge(e)
    t2 = time.perf_counter()
    out.update(add_vertex=(t1 - t0) / nv * 1e6, add_edge=(t2 - t1) / m * 1e6)
    opt = SparseOptimizer()
    t0 = time.perf_counter()
    opt.add_vertices(VertexSE3Expmap, np.arange(nk), T, fixed=np.arange(nk) >= nfree)
    opt.add_vertices(VertexPointXYZ, nk + np.arange(npts), X, marginalized=True)
    opt.add_edges(EdgeSE3ProjectXYZ, ids, meas, information=np.eye(2)[None] *
                  inv_sigma2[octave][:, None, None], robust_kernel=shared, params=cam)
    out["bulk"] = (time.perf_counter() - t0) * 1e3
    return out


def _run(src: Path | None, per_edge_kernel: bool) -> dict[str, float]:
    cmd = [sys.executable, "-P", __file__, "--worker"]
    if src is not None:
        cmd += ["--src", str(src)]
    if per_edge_kernel:
        cmd.append("--per-edge-kernel")
    res = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=600)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref", default="main", help="the 'before' revision (git)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--src", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--per-edge-kernel", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        if args.src is not None:
            _import_from(args.src)
        print(json.dumps(worker(args.per_edge_kernel)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.ref], check=True,
                                 capture_output=True).stdout
        with tarfile.open(fileobj=__import__("io").BytesIO(archive)) as tar:
            tar.extractall(tmp, filter="data")
        runs: dict[str, list[dict[str, float]]] = {"before": [], "after": [], "after, kernel "
                                                   "per edge": []}
        for _ in range(args.repeats):  # interleaved
            runs["before"].append(_run(Path(tmp), False))
            runs["after"].append(_run(None, False))
            runs["after, kernel per edge"].append(_run(None, True))
    keys = ["vertex", "add_vertex", "edge", "add_edge", "flush", "build", "estimate", "bulk"]
    print(f"per object, µs (bulk: ms); medians of {args.repeats}; before = {args.ref}")
    print(f"{'':24}" + "".join(f"{k:>11}" for k in keys))
    med = {name: {k: statistics.median(r[k] for r in rs) for k in keys}
           for name, rs in runs.items()}
    for name, row in med.items():
        print(f"{name:24}" + "".join(f"{row[k]:11.2f}" for k in keys))
    b, a = med["before"], med["after"]
    print("before / after:        " + "".join(f"{b[k] / a[k]:11.1f}" if a[k] else f"{'-':>11}"
                                           for k in keys))
    print("targets (issue 23): add_vertex <= 5 µs, add_edge <= 10 µs, estimate <= 5 µs")


if __name__ == "__main__":
    main()
