"""Benchmark of the J criterion (paper eq. 40-46, Algorithm 2): batched vs floor vs dense.

Table 1 times ``j_criterion`` on ``[Z, K, n, B]`` designs (Z = 5 repeats, K = 4 candidates,
B = 110, as in the batting experiment) against

- the floor: the two batched products ``Xᵀ diag(w) X`` and ``Xᵀ diag(w²) X`` in their fastest
  form, which any implementation of J has to compute;
- the dense form of Algorithm 2: for each of the Z·K sets, ``L = (A + λI)^{-1} X̂ᵀ W / n`` as a
  ``B × n`` matrix and ``J = tr(Ũ L Lᵀ)``, in a Python loop, with W applied as a row scaling;
- the same with W built as the ``n × n`` diagonal matrix eq. 44-46 write (the paper's literal
  form; only up to ``LITERAL_MAX_N``, beyond which W alone takes hundreds of MB).

Table 2 times J on chain-walk-like designs (20 distinct rows of width B = 12) on the raw rows vs
after :func:`aggregate_identical_rows`, showing that J's cost stops growing with n.

Run::

    python benchmarks/bench_j.py                  # full run, about 1-2 minutes on 2 cores
    python benchmarks/bench_j.py --quick          # smoke test, a few seconds
    python benchmarks/bench_j.py --out results/bench_j.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, fields
from pathlib import Path

import torch
from _aggregate import aggregate_identical_rows
from _timing import machine_info, median_times

from torch_api.core.solve import DEFAULT_LAMBDA, j_criterion

DTYPE = torch.float64
REL_TOL = 1e-8  # agreement required between the forms of J (relative)
GOAL_FLOOR_RATIO = 1.5  # batched J at most this many times the floor, at every n
GOAL_DENSE_SPEEDUP = 3.0  # batched J at least this many times faster than dense ...
GOAL_DENSE_N = 2000  # ... at this n
LITERAL_MAX_N = 3000  # the literal n × n W of eq. 46 is timed up to this n


@dataclass
class Args:
    """Command-line arguments of the benchmark."""

    quick: bool = False
    """Tiny sizes and budgets, for a smoke test (< 10 s)."""
    out: Path | None = None
    """Write the numbers as JSON to this path."""
    seed: int = 0
    """Seed of the random designs."""
    repeats_z: int = 5
    """Z, the number of repeats of the J estimate."""
    candidates_k: int = 4
    """K, the number of candidate sampling policies."""
    features_b: int = 110
    """B, the number of basis functions of table 1 (batting: 110)."""
    dense_ns: tuple[int, ...] = (100, 300, 1000, 2000, 3000, 10000)
    """Sample counts n of table 1."""
    finite_ns: tuple[int, ...] = (100, 1000, 10000, 30000, 100000)
    """Sample counts n of table 2 (finite state space)."""
    distinct_rows: int = 20
    """Distinct psi_hat rows of table 2 (chain walk: S × A = 20)."""
    finite_b: int = 12
    """B of table 2 (chain walk: 12)."""
    budget_s: float = 1.0
    """Time budget of one measurement (repeats adapt to it, at least 3)."""

    def __post_init__(self) -> None:
        if self.quick:
            self.dense_ns = (100, 300)
            self.finite_ns = (100, 2000)
            self.budget_s = 0.1


def parse_args() -> Args:
    """Fill :class:`Args` from the command line (``--out PATH``, ``--quick``, ...)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a smoke test (< 10 s)")
    parser.add_argument("--out", type=Path, default=None, help="write the numbers as JSON here")
    parser.add_argument("--seed", type=int, default=Args.seed)
    parser.add_argument("--budget-s", type=float, default=Args.budget_s, help="s per measurement")
    ns = parser.parse_args()
    return Args(quick=ns.quick, out=ns.out, seed=ns.seed, budget_s=ns.budget_s)


def importance_weights(shape: tuple[int, ...], gen: torch.Generator) -> torch.Tensor:
    """Positive weights with an importance-weight-like spread (log-normal)."""
    return torch.exp(0.5 * torch.randn(shape, generator=gen, dtype=DTYPE))


def u_tilde(x0: torch.Tensor, w0: torch.Tensor) -> torch.Tensor:
    """Ũ = (1/n0) Σ w x xᵀ over a reward-free design ``[Z, n0, B]`` -> ``[Z, 1, B, B]``."""
    xw = x0 * w0.sqrt().unsqueeze(-1)
    return (xw.mT @ xw / x0.shape[-2]).unsqueeze(1)


def floor_moments(x: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The floor: ``Xᵀ diag(w) X`` and ``Xᵀ diag(w²) X`` as ``(x √w)ᵀ (x √w)``, ``(x w)ᵀ (x w)``."""
    xw = x * w.sqrt().unsqueeze(-1)
    xw2 = x * w.unsqueeze(-1)  # √(w²) = w for w ≥ 0
    return xw.mT @ xw, xw2.mT @ xw2


def dense_j(x: torch.Tensor, w: torch.Tensor, u: torch.Tensor, lam: float) -> torch.Tensor:
    """Algorithm 2 written out per set: ``L`` as a ``B × n`` matrix, ``J = tr(Ũ L Lᵀ)``.

    ``x`` ``[Z, K, n, B]``, ``w`` ``[Z, K, n]``, ``u`` ``[Z, 1, B, B]`` -> J ``[Z, K]``.
    """
    num_z, num_k, n, b = x.shape
    eye = torch.eye(b, dtype=x.dtype)
    out = torch.empty(num_z, num_k, dtype=x.dtype)
    for z in range(num_z):
        for k in range(num_k):
            big_b = x[z, k].T * w[z, k] / n  # B = (1/n) Xᵀ W, [B, n]
            a = big_b @ x[z, k]  # A = (1/n) Xᵀ W X
            ell = torch.linalg.solve(a + lam * eye, big_b)  # L, [B, n]
            out[z, k] = torch.trace(u[z, 0] @ ell @ ell.T)
    return out


def dense_j_literal(x: torch.Tensor, w: torch.Tensor, u: torch.Tensor, lam: float) -> torch.Tensor:
    """Algorithm 2 exactly as eq. 44-46 write it: W an ``n × n`` diagonal matrix, per set."""
    num_z, num_k, n, b = x.shape
    eye = torch.eye(b, dtype=x.dtype)
    out = torch.empty(num_z, num_k, dtype=x.dtype)
    for z in range(num_z):
        for k in range(num_k):
            big_w = torch.diag(w[z, k])  # eq. 46, [n, n]
            big_b = x[z, k].T @ big_w / n  # [B, n]
            a = big_b @ x[z, k]
            ell = torch.linalg.solve(a + lam * eye, big_b)
            out[z, k] = torch.trace(u[z, 0] @ ell @ ell.T)
    return out


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest relative difference between two J tensors."""
    return ((a - b).abs() / b.abs()).max().item()


def table_dense(args: Args, gen: torch.Generator) -> list[dict]:
    """Table 1: batched ``j_criterion`` vs the floor vs the dense Algorithm 2, per n."""
    z, k, b = args.repeats_z, args.candidates_k, args.features_b
    x0 = torch.randn(z, 500, b, generator=gen, dtype=DTYPE)  # reward-free design of Ũ
    u = u_tilde(x0, importance_weights((z, 500), gen))
    rows = []
    for n in args.dense_ns:
        x = torch.randn(z, k, n, b, generator=gen, dtype=DTYPE)
        w = importance_weights((z, k, n), gen)
        methods = {
            "batched": lambda x=x, w=w: j_criterion(x, w, u),
            "floor": lambda x=x, w=w: floor_moments(x, w),
            "dense": lambda x=x, w=w: dense_j(x, w, u, DEFAULT_LAMBDA),
        }
        if n <= LITERAL_MAX_N:
            methods["literal"] = lambda x=x, w=w: dense_j_literal(x, w, u, DEFAULT_LAMBDA)
        timings = median_times(methods, budget_s=args.budget_s)
        literal = timings.get("literal")
        if literal is not None and not rel_err(literal.result, timings["dense"].result) <= REL_TOL:
            raise RuntimeError(f"literal and dense J disagree at n = {n}")
        batched, floor, dense = timings["batched"], timings["floor"], timings["dense"]
        err = rel_err(batched.result, dense.result)
        if not err <= REL_TOL:
            raise RuntimeError(f"batched and dense J disagree at n = {n}: relative error {err:.3g}")
        rows.append(
            {
                "n": n,
                "batched": batched.as_dict(),
                "floor": floor.as_dict(),
                "dense": dense.as_dict(),
                "batched_over_floor": batched.median_ms / floor.median_ms,
                "dense_over_batched": dense.median_ms / batched.median_ms,
                "literal": literal.as_dict() if literal else None,
                "literal_over_batched": literal.median_ms / batched.median_ms if literal else None,
                "rel_err_dense": err,
            }
        )
        print(f"  n = {n}: done", flush=True)
    return rows


def chain_walk_design(
    args: Args, n: int, rows: torch.Tensor, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """``[Z, K, n, B]`` design whose rows are drawn at random from ``rows`` ``[G, B]``."""
    shape = (args.repeats_z, args.candidates_k, n)
    idx = torch.randint(rows.shape[0], shape, generator=gen)
    return rows[idx], importance_weights(shape, gen)


def j_aggregated(x: torch.Tensor, w: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """J after merging identical rows (the aggregation is part of the cost)."""
    agg = aggregate_identical_rows(x, w)
    return j_criterion(agg.x, agg.w, u, num_samples=agg.num_samples, sq_weights=agg.sq_weights)


def table_finite(args: Args, gen: torch.Generator) -> list[dict]:
    """Table 2: J on the raw rows vs aggregate + J, on a finite state space, per n."""
    distinct = torch.randn(args.distinct_rows, args.finite_b, generator=gen, dtype=DTYPE)
    x0, w0 = chain_walk_design(args, 500, distinct, gen)
    u = u_tilde(x0[:, 0], w0[:, 0])
    rows = []
    for n in args.finite_ns:
        x, w = chain_walk_design(args, n, distinct, gen)
        agg = aggregate_identical_rows(x, w)
        timings = median_times(
            {
                "raw": lambda x=x, w=w: j_criterion(x, w, u),
                "aggregate_and_j": lambda x=x, w=w: j_aggregated(x, w, u),
                "j_on_aggregate": lambda agg=agg: j_criterion(
                    agg.x, agg.w, u, num_samples=agg.num_samples, sq_weights=agg.sq_weights
                ),
            },
            budget_s=args.budget_s,
        )
        raw, agg_total, agg_j = (
            timings[key] for key in ("raw", "aggregate_and_j", "j_on_aggregate")
        )
        err = rel_err(agg_total.result, raw.result)
        if not err <= REL_TOL:
            raise RuntimeError(f"raw and aggregated J disagree at n = {n}: relative error {err}")
        rows.append(
            {
                "n": n,
                "distinct_rows": agg.x.shape[-2],
                "raw": raw.as_dict(),
                "aggregate_and_j": agg_total.as_dict(),
                "j_on_aggregate": agg_j.as_dict(),
                "raw_over_aggregated": raw.median_ms / agg_total.median_ms,
                "rel_err_aggregated": err,
            }
        )
        print(f"  n = {n}: done", flush=True)
    return rows


def markdown_dense(rows: list[dict], args: Args) -> str:
    """Table 1 as Markdown."""
    lines = [
        f"J for Z = {args.repeats_z} × K = {args.candidates_k} sets, B = {args.features_b}, "
        "float64 (median ms)",
        "",
        "| n | batched J | floor (2 matmuls) | dense Alg. 2 | dense, W n×n | batched / floor "
        "| dense / batched | dense W n×n / batched |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        literal = f"{r['literal']['median_ms']:.2f}" if r["literal"] else "—"
        literal_ratio = f"{r['literal_over_batched']:.1f}×" if r["literal"] else "—"
        lines.append(
            f"| {r['n']:,} | {r['batched']['median_ms']:.2f} | {r['floor']['median_ms']:.2f} "
            f"| {r['dense']['median_ms']:.2f} | {literal} | {r['batched_over_floor']:.2f}× "
            f"| {r['dense_over_batched']:.1f}× | {literal_ratio} |"
        )
    return "\n".join(lines)


def markdown_finite(rows: list[dict], args: Args) -> str:
    """Table 2 as Markdown."""
    lines = [
        f"J on a finite state space: Z = {args.repeats_z} × K = {args.candidates_k} sets, "
        f"B = {args.finite_b}, {args.distinct_rows} distinct rows, float64 (median ms)",
        "",
        "| n | distinct rows | J on raw rows | aggregate + J | J on aggregate | raw / (agg. + J) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']:,} | {r['distinct_rows']} | {r['raw']['median_ms']:.2f} "
            f"| {r['aggregate_and_j']['median_ms']:.2f} | {r['j_on_aggregate']['median_ms']:.2f} "
            f"| {r['raw_over_aggregated']:.1f}× |"
        )
    return "\n".join(lines)


def goals(rows: list[dict]) -> dict:
    """Check the two goals of table 1."""
    worst = max(rows, key=lambda r: r["batched_over_floor"])
    at_n = [r for r in rows if r["n"] == GOAL_DENSE_N]
    return {
        "floor_ratio_max": worst["batched_over_floor"],
        "floor_ratio_max_at_n": worst["n"],
        "floor_goal_met": worst["batched_over_floor"] <= GOAL_FLOOR_RATIO,
        "dense_speedup_at_goal_n": at_n[0]["dense_over_batched"] if at_n else None,
        "dense_goal_met": (at_n[0]["dense_over_batched"] >= GOAL_DENSE_SPEEDUP) if at_n else None,
        "literal_speedup_at_goal_n": at_n[0]["literal_over_batched"] if at_n else None,
    }


def main(args: Args) -> dict:
    """Run both tables, print them, and return all numbers."""
    info = machine_info()
    print(
        f"# bench_j: torch {info['torch']}, {info['threads']} threads, "
        f"{info['cpu']} ({info['cpu_count']} CPUs), Python {info['python']}, "
        f"load average {info['load_avg_1min']:.2f}" + (" [quick]" if args.quick else ""),
        flush=True,
    )
    gen = torch.Generator().manual_seed(args.seed)
    start = time.perf_counter()
    print("table 1 (batched / floor / dense) ...", flush=True)
    dense_rows = table_dense(args, gen)
    print("table 2 (finite state space) ...", flush=True)
    finite_rows = table_finite(args, gen)
    verdict = goals(dense_rows)

    print()
    print(markdown_dense(dense_rows, args))
    print()
    print(
        f"Goal batched ≤ {GOAL_FLOOR_RATIO}× floor at every n: "
        f"{'met' if verdict['floor_goal_met'] else 'NOT met'} (worst "
        f"{verdict['floor_ratio_max']:.2f}× at n = {verdict['floor_ratio_max_at_n']:,})."
    )
    if verdict["dense_goal_met"] is not None:
        print(
            f"Goal dense ≥ {GOAL_DENSE_SPEEDUP}× slower than batched at n = {GOAL_DENSE_N:,}: "
            f"{'met' if verdict['dense_goal_met'] else 'NOT met'} against the row-scaled "
            f"dense form ({verdict['dense_speedup_at_goal_n']:.1f}×), "
            f"{verdict['literal_speedup_at_goal_n']:.1f}× against the literal n × n W."
        )
    print(
        "Batched and dense J agree: max relative error "
        f"{max(r['rel_err_dense'] for r in dense_rows):.1e} (tolerance {REL_TOL:g})."
    )
    print()
    print(markdown_finite(finite_rows, args))
    print()
    print(
        "Raw and aggregated J agree: max relative error "
        f"{max(r['rel_err_aggregated'] for r in finite_rows):.1e} (tolerance {REL_TOL:g})."
    )
    total = time.perf_counter() - start
    info["load_avg_1min_end"] = os.getloadavg()[0]
    print(f"\n(total {total:.1f} s; load average at the end {info['load_avg_1min_end']:.2f})")

    results = {
        "machine": info,
        "args": {f.name: getattr(args, f.name) for f in fields(args) if f.name != "out"},
        "dense": dense_rows,
        "finite": finite_rows,
        "goals": verdict,
        "total_s": total,
    }
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main(parse_args())
