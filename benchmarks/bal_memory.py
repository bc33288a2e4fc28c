"""Memory of a ``graphopt-bal`` run, array by array, in bytes per observation.

Builds the optimizer as ``graphopt-bal`` does (cameras, marginalised points, one projection
edge per observation), then lists every numpy array reachable from the live objects — the
problem read from the file, the graph's stores and groups, the structure (block index,
pattern, assembler terms, Schur strategies, solver), and the per-iteration arrays of one
linearisation and one damped reduction (Jacobians, weighted Jacobians and errors, the assembled
U/V/W blocks and gradient, the V factors, ``S``'s data) — with its owner's path and its size
in bytes per observation. An array shared by several owners (a view, or the same object) is
counted once, under the first path that reaches it.

Each phase's peak of numpy allocations is measured with ``tracemalloc`` (numpy reports its
buffers to it; CHOLMOD's factor is outside it and is measured as the growth of the process's
RSS), and the process's peak RSS at the end.

Usage (one thread; from outside the repository root, or with ``python -P``)::

    python -P benchmarks/bal_memory.py FILE [--solver cholmod] [--top 40] [--json out.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from collections import defaultdict  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402


def _rss_mib() -> float:
    """Current resident set size (MiB), from /proc."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class Inventory:
    """Bytes of every numpy buffer reachable from objects, by the first path that reaches it;
    a buffer already counted by an earlier :meth:`add` is not counted again.

    Args:
        max_depth: Deepest attribute path followed.
    """

    def __init__(self, max_depth: int = 12) -> None:
        self.max_depth = max_depth
        self._objects: set[int] = set()
        self._buffers: set[int] = set()

    def add(self, roots: dict[str, Any]) -> dict[str, int]:
        """Walk ``roots``; ``{path: bytes}`` of the buffers not seen before.

        Args:
            roots: Named objects to walk.
        """
        out: dict[str, int] = {}
        for name, obj in roots.items():
            self._walk(obj, name, 0, out)
        return out

    def _walk(self, obj: Any, path: str, depth: int, out: dict[str, int]) -> None:
        if id(obj) in self._objects or depth > self.max_depth:
            return
        self._objects.add(id(obj))
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            key = base.__array_interface__["data"][0]
            if key not in self._buffers and base.nbytes:
                self._buffers.add(key)
                out[path] = out.get(path, 0) + base.nbytes
            return
        if isinstance(obj, (str, bytes, int, float, bool, type(None), type)):
            return
        if isinstance(obj, dict):
            for k, v in obj.items():
                key = f"[{k!r}]" if not isinstance(k, (tuple, type)) else "[..]"
                self._walk(v, path + key, depth + 1, out)
            return
        if isinstance(obj, (list, tuple)):
            for i, v in enumerate(obj):
                self._walk(v, f"{path}[{i}]", depth + 1, out)
            return
        mod = type(obj).__module__ or ""
        if not (mod.startswith(("graphopt", "scipy.sparse", "sksparse")) or sp.issparse(obj)):
            return
        attrs = dict(vars(obj)) if hasattr(obj, "__dict__") else {}
        if dataclasses.is_dataclass(obj):
            attrs.update({f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)})
        for k, v in attrs.items():
            self._walk(v, f"{path}.{k}", depth + 1, out)


def _group(path: str) -> str:
    """A path with list indices collapsed (``terms[0].hterms[3]`` → ``terms[].hterms[]``)."""
    import re

    return re.sub(r"\[\d+\]", "[]", path)


def run(path: str, solver: str, top: int) -> dict[str, Any]:
    """Measure one file.

    Args:
        path: BAL file.
        solver: graphopt linear solver.
        top: Rows of the printed table.
    """
    from graphopt import LevenbergConfig, SparseOptimizer
    from graphopt.io.bal import read_bal
    from graphopt.linear import schur_strategy
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
    from graphopt.types.vertices import VertexPointXYZ

    phases: dict[str, dict[str, float]] = {}
    tracemalloc.start()

    def phase(name: str, t0: float) -> None:
        cur, peak = tracemalloc.get_traced_memory()
        phases[name] = {"seconds": time.perf_counter() - t0, "traced_mib": cur / 2**20,
                        "traced_peak_mib": peak / 2**20, "rss_mib": _rss_mib()}
        tracemalloc.reset_peak()

    t0 = time.perf_counter()
    problem = read_bal(path)
    phase("read", t0)
    m = problem.num_observations
    t0 = time.perf_counter()
    opt = SparseOptimizer(algorithm=LevenbergConfig(), solver=solver, verbose=False)
    nc, npt = problem.num_cameras, problem.num_points
    opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), problem.points, marginalized=True)
    opt.add_edges(EdgeBALProjection,
                  np.column_stack([problem.camera_index, nc + problem.point_index]),
                  problem.observations)
    phase("add", t0)
    t0 = time.perf_counter()
    opt.initialize_optimization()
    phase("initialize", t0)
    prob = opt.problem
    inv = Inventory()
    structure = inv.add({"problem": problem, "graph": opt.graph, "linearizer": prob.linearizer,
                           "system": prob.system, "solver": prob.solver,
                           "updates": prob._updates})  # noqa: SLF001

    captured: dict[str, Any] = {}
    orig_lin = prob.linearizer.linearize

    def lin_hook() -> Any:
        out = orig_lin()
        captured["lin"] = out[0]
        return out

    prob.linearizer.linearize = lin_hook  # type: ignore[method-assign]
    orig_init = schur_strategy.VFactors.__init__

    def vf_hook(self: Any, *a: Any, **k: Any) -> None:
        orig_init(self, *a, **k)
        captured["factors"] = self

    schur_strategy.VFactors.__init__ = vf_hook  # type: ignore[method-assign]
    t0 = time.perf_counter()
    asm, _ = prob.linearize()
    phase("linearize", t0)
    t0 = time.perf_counter()
    damp = prob.damping(asm, True)
    s, rhs, vinv = prob.system.reduce(asm, 1e-4, damp)
    phase("schur", t0)
    t0 = time.perf_counter()
    rss_before = _rss_mib()
    du = prob.solver.solve(s, rhs)
    phase("solve", t0)
    phases["solve"]["rss_growth_mib"] = _rss_mib() - rss_before
    prob.system.back_substitute(asm, du, vinv)
    # The implicit-Schur path makes no V factors and hands over an operator instead of S.
    per_iter = inv.add({"lin": captured["lin"], "asm": asm, "damp": damp,
                          "factors": captured.get("factors"), "s_data": s, "rhs": rhs})
    schur_strategy.VFactors.__init__ = orig_init  # type: ignore[method-assign]
    tracemalloc.stop()

    rows: dict[str, int] = defaultdict(int)
    for table, prefix in ((structure, "kept"), (per_iter, "iteration")):
        for p, b in table.items():
            rows[f"{prefix}: {_group(p)}"] += b
    total_kept = sum(structure.values())
    total_iter = sum(per_iter.values())
    print(f"{path}: {nc} cameras, {npt} points, {m} observations; solver {solver}")
    for name, ph in phases.items():
        extra = (f", RSS growth {ph['rss_growth_mib']:.0f} MiB (CHOLMOD)"
                 if "rss_growth_mib" in ph else "")
        print(f"  {name:<10} {ph['seconds']:7.2f} s  numpy live {ph['traced_mib']:8.0f} MiB, "
              f"phase peak {ph['traced_peak_mib']:8.0f} MiB, RSS {ph['rss_mib']:7.0f} MiB{extra}")
    print(f"  peak RSS {_peak_rss_mib():.0f} MiB = {_peak_rss_mib() * 2**20 / m:.0f} B/obs")
    print(f"  arrays kept between iterations {total_kept / m:7.1f} B/obs, per iteration "
          f"{total_iter / m:7.1f} B/obs")
    print(f"  {'B/obs':>8}  owner")
    for p, b in sorted(rows.items(), key=lambda kv: -kv[1])[:top]:
        print(f"  {b / m:8.1f}  {p}")
    return {"file": path, "observations": m, "phases": phases, "peak_rss_mib": _peak_rss_mib(),
            "bytes_per_observation": {p: b / m for p, b in rows.items()}}


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        argv: Arguments (``sys.argv[1:]`` if None).
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("file")
    ap.add_argument("--solver", default="cholmod")
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    out = run(args.file, args.solver, args.top)
    if args.json:
        from graphopt.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
