"""Reference numbers of the ball-batting task (paper section 5).

1. The reference optimum: the best of all 2^10 = 1024 open-loop action sequences without noise.
2. A uniformly random policy with the torque noise: the share of episodes in which the bat hits
   the ball and the distribution of the carry over those hits.

Writes them as JSON (``examples/train_batting.py`` draws the optimum in its figure).

    python examples/batting_reference.py --episodes 1000 --seed 0
"""

import itertools
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from envs.batting import ACTION_TORQUES, MAX_STEPS, BattingEnv, BattingSimulator

ACTION_NAMES = ("cock", "swing")  # action 0 = (50, -35) N m, action 1 = (-50, 10) N m


@dataclass(frozen=True)
class Args:
    """The reference numbers' arguments."""

    episodes: int = 1000
    """noisy episodes of the uniformly random policy"""
    seed: int = 0
    """seed of the torque noise and of the random actions"""
    out: str = "results/batting_reference.json"
    """the JSON file the summary goes to (its folder is created)"""


def reference_optimum() -> dict:
    """Best noiseless open-loop sequence over all 2^N of them, and a few comparisons."""
    seqs = np.array(list(itertools.product((0, 1), repeat=MAX_STEPS)), dtype=np.int64)
    sim = BattingSimulator(num_envs=len(seqs))
    sim.reset()
    torques = np.asarray(ACTION_TORQUES)
    for t in range(MAX_STEPS):
        sim.step(torques[seqs[:, t]])
    best = int(np.argmax(sim.carry))
    swing_now = int(np.flatnonzero((seqs == 1).all(axis=1))[0])
    order = np.argsort(-sim.carry)[:5]
    return {
        "best_sequence": seqs[best].tolist(),
        "best_carry": float(sim.carry[best]),
        "swing_at_once_carry": float(sim.carry[swing_now]),
        "sequences_hitting": int(sim.hit.sum()),
        "top5": [(seqs[i].tolist(), float(sim.carry[i])) for i in order],
    }


def random_policy(episodes: int, seed: int) -> dict:
    """Hit share and carries of a uniformly random policy over ``episodes`` noisy episodes."""
    env = BattingEnv(batch_size=episodes, seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    td = env.reset()
    total = torch.zeros(episodes)
    hits = torch.zeros(episodes, dtype=torch.long)
    for _ in range(MAX_STEPS):
        td["action"] = torch.randint(0, 2, (episodes,), generator=gen)
        td = env.step(td)
        reward = td["next", "reward"].squeeze(-1)
        hits += (reward > 0).long()
        total += reward
        td = td["next"]
    hit = env.hit.numpy()
    carry = total.numpy()[hit]
    q = np.quantile(carry, [0.05, 0.25, 0.5, 0.75, 0.95]) if len(carry) else [np.nan] * 5
    return {
        "episodes": episodes,
        "hit_share": float(hit.mean()),
        "max_rewards_per_episode": int(hits.max()),
        "carry_mean": float(carry.mean()) if len(carry) else None,
        "carry_min": float(carry.min()) if len(carry) else None,
        "carry_max": float(carry.max()) if len(carry) else None,
        "carry_quantiles_5_25_50_75_95": [float(x) for x in q],
    }


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    out = Path(args.out)
    try:  # checked before any work: one line naming the value, exit 2
        if args.episodes < 1 or args.seed < 0:
            raise ValueError(
                f"episodes must be >= 1 and seed >= 0, got {args.episodes}, {args.seed}"
            )
        out.parent.mkdir(parents=True, exist_ok=True)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None

    opt = reference_optimum()
    names = " ".join(ACTION_NAMES[a] for a in opt["best_sequence"])
    print(f"reference optimum (noiseless, best of 1024): {opt['best_sequence']} = {names}")
    print(
        f"  carry {opt['best_carry']:.2f} m; swinging at once: {opt['swing_at_once_carry']:.2f} m;"
    )
    print(f"  {opt['sequences_hitting']} of 1024 sequences hit the ball")
    for seq, carry in opt["top5"]:
        print(f"  {''.join(map(str, seq))}  {carry:.2f} m")

    rnd = random_policy(args.episodes, args.seed)
    q = ", ".join(f"{x:.2f}" for x in rnd["carry_quantiles_5_25_50_75_95"])
    print(f"random policy, {rnd['episodes']} noisy episodes: hit share {rnd['hit_share']:.3f}")
    if rnd["carry_mean"] is not None:
        print(
            f"  carry mean {rnd['carry_mean']:.2f} m, min {rnd['carry_min']:.2f}, "
            f"max {rnd['carry_max']:.2f}; quantiles 5/25/50/75/95 %: {q}"
        )

    result = {"args": asdict(args), "reference_optimum": opt, "random_policy": rnd}
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
