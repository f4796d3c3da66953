"""Time per iteration of an active batting run, split into its parts, each next to its floor.

Runs ``ActivePolicyIteration`` (mode active, the 'decreasing' schedule, Z = 5, K = 4, the
paper's basis, B = 110) on T batched trials and times, per iteration, with timers wrapped
around the library's functions:

* physics: MuJoCo's rollouts inside the env (``BattingSimulator._run``); floor: bare
  ``mujoco.batch`` replaying a sample of the run's own rollouts (``_physics_floor.py``), scaled
  to the iteration's counted steps;
* kernels: ``GaussianActionBasis.kernels`` (policies' Q-values and psi_hat); floor: one
  ``torch.exp`` over an output of the same size (the one transcendental pass any form needs);
* moments: ``weighted_moment`` (``Σ w x xᵀ``, for J's ``A``, ``C``, ``Ũ`` and the fits);
  floor: the product ``xᵀ x`` alone on the same shapes;
* solves: ``j_from_moments`` and ``weighted_ridge`` (Cholesky factorisations and solves);
  floor: batched ``B × B`` matrix products of the same batch shapes and the same flop count
  (a factorisation ``B³/3``, a solve with ``m`` right-hand sides ``2 B² m``; a product
  ``2 B³``);
* the rest: env Python, TorchRL rollouts, policies, buffers.

Every floor is timed in the same invocation, after the run, on the shapes the run recorded.

    python benchmarks/bench_batting_iteration.py --trials 32
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from pathlib import Path

import torch
from _physics_floor import PhysicsAudit, replay_batch
from profile_batting import active_run, run_arguments

import torch_api.core.criterion
import torch_api.core.fit
import torch_api.core.solve
from envs import batting
from envs.batting import BattingEnv
from torch_api.core.basis import GaussianActionBasis

PARTS = ("physics", "kernels", "moments", "solves")
TIMERS: dict[str, float] = defaultdict(float)
SHAPES: dict[str, list] = defaultdict(list)  # per part: what its floor replays


def timed(owner, attr: str, part: str, shapes=None) -> None:
    """Wrap ``owner.attr`` to add its time to ``TIMERS[part]`` (outermost call only)."""
    original = getattr(owner, attr)
    depth = {"n": 0}

    def wrapper(*args, **kwargs):
        if depth["n"]:
            return original(*args, **kwargs)
        depth["n"] += 1
        start = time.perf_counter()
        try:
            out = original(*args, **kwargs)
        finally:
            depth["n"] -= 1
            TIMERS[part] += time.perf_counter() - start
        if shapes is not None:
            SHAPES[part].append(shapes(args, kwargs, out))
        return out

    setattr(owner, attr, wrapper)


def instrument() -> None:
    timed(batting.BattingSimulator, "_run", "physics")
    timed(GaussianActionBasis, "kernels", "kernels", lambda a, k, out: out.numel())
    for module in (torch_api.core.solve, torch_api.core.criterion):
        timed(module, "weighted_moment", "moments", lambda a, k, out: tuple(a[0].shape))
    timed(torch_api.core.criterion, "j_from_moments", "solves", _j_shape)
    timed(torch_api.core.fit, "weighted_ridge", "solves", _ridge_shape)


def _j_shape(args, kwargs, out) -> tuple:
    a = args[0]  # [..., B, B]: a factorisation and two solves with B right-hand sides
    b = a.shape[-1]
    return tuple(a.shape[:-2]), b, b**3 / 3 + 2 * (2 * b * b * b)


def _ridge_shape(args, kwargs, out) -> tuple:
    x = args[0]  # [..., n, B]: a factorisation and one solve with one right-hand side
    b = x.shape[-1]
    return tuple(x.shape[:-2]), b, b**3 / 3 + 2 * b * b


def best_of(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def floors(audit: PhysicsAudit, nthread: int) -> dict[str, float]:
    """The floor of each part over the whole run, timed here on the run's recorded shapes."""
    cache: dict = {}

    def once(key, fn):
        if key not in cache:
            cache[key] = best_of(fn)
        return cache[key]

    f64 = torch.float64
    kernels = sum(
        once(("exp", n), lambda n=n: torch.exp(torch.rand(n, dtype=f64))) for n in SHAPES["kernels"]
    )
    moments = 0.0
    for shape in SHAPES["moments"]:
        x = torch.rand(shape, dtype=f64)
        moments += once(("mm", shape), lambda x=x: x.mT @ x)
    solves = 0.0
    for lead, b, flops in SHAPES["solves"]:
        m = torch.rand(*lead, b, b, dtype=f64)
        product = once(("bmm", lead, b), lambda m=m: m @ m)
        solves += product * flops / (2 * b**3)
    return {
        "physics": sum(replay_batch(audit, nthread=nthread).values()),
        "kernels": kernels,
        "moments": moments,
        "solves": solves,
    }


def main() -> dict:
    args = run_arguments(__doc__, trials=32, audit=0.02, out="results/bench_batting_iteration.json")
    audit = PhysicsAudit(args.audit, seed=0)
    instrument()
    api = active_run(
        args, lambda rows: BattingEnv(batch_size=rows, nthread=args.nthread, hook=audit)
    )
    rows, steps = [], []
    for _ in range(len(api.schedule)):
        before, counted = dict(TIMERS), sum(audit.steps.values())
        start = time.perf_counter()
        api.step()
        wall = time.perf_counter() - start
        rows.append({"wall": wall} | {p: TIMERS[p] - before.get(p, 0.0) for p in PARTS})
        steps.append(sum(audit.steps.values()) - counted)
    floor = floors(audit, args.nthread)
    total = {key: sum(r[key] for r in rows) for key in ("wall", *PARTS)}
    print(
        f"\nActive run, {args.trials} trials, schedule {list(api.schedule)}, torch threads "
        f"{args.threads}, MuJoCo threads {args.nthread}: {total['wall']:.1f} s; "
        f"{audit.steps['coarse']:,} coarse + {audit.steps['fine']:,} fine physics steps\n"
    )
    print("| l | wall s | " + " | ".join(PARTS) + " | rest |")
    print("|---:|---:|" + "---:|" * (len(PARTS) + 1))
    for i, r in enumerate(rows):
        rest = r["wall"] - sum(r[p] for p in PARTS)
        cells = " | ".join(f"{r[p]:.2f}" for p in PARTS)
        print(f"| {i + 1} | {r['wall']:.2f} | {cells} | {rest:.2f} |")
    rest = total["wall"] - sum(total[p] for p in PARTS)
    print(f"| all | {total['wall']:.2f} | " + " | ".join(f"{total[p]:.2f}" for p in PARTS), end="")
    print(f" | {rest:.2f} |")
    floor_cells = " | ".join(f"{floor[p]:.2f}" for p in PARTS)
    print(f"| floor | {sum(floor.values()):.2f} | {floor_cells} | |")
    print("| part / floor | | " + " | ".join(f"{total[p] / floor[p]:.1f}×" for p in PARTS) + " | |")
    print(
        "\nfloors: physics = bare mujoco.batch replaying a "
        f"{args.audit:.0%} sample of the run's rollouts; kernels = one exp over the same "
        "outputs; moments = xᵀx alone; solves = matrix products of the same flop count"
    )
    payload = {"args": vars(args), "iterations": rows, "total": total, "floor": floor}
    payload["physics_steps"] = dict(audit.steps)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(payload, indent=1))
    return payload


if __name__ == "__main__":
    main()
