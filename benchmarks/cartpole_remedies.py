"""CartPole-v1 beyond the paper's horizon: why good policies are lost, and remedies measured.

The setting of the long-horizon issue (#25), as a new user would try it: Gymnasium's
``CartPole-v1`` through TorchRL's ``GymWrapper`` with its default one-hot actions (E copies in
one ``SyncVectorEnv``, so that T trials run as one batch), ``ObservationNorm`` to unit scale
(``s / (2.4, 2, 0.21, 2)``), a 3⁴ Gaussian grid on ``{-1, 0, 1}⁴`` with τ = 1 (B = 164),
γ = 0.95, 6 iterations of 5 rewarded episodes of at most 200 steps. The performance of pi_{l+1}
is the greedy return: steps until the first done, capped at 500, mean of 5 episodes.

Each configuration changes one thing of the baseline (``REMEDIES``); all run on the same trial
seeds (paired). The table gives the mean greedy return per iteration over trials, how many
trials end at ≥ 475, how many reached ≥ 475 and lost it by the end ("lost"), and the fit's mean
flattening ν and effective sample size (ESS, in % of the rewarded samples) at the last
iteration.

Run::

    python benchmarks/cartpole_remedies.py --trials 8 --threads 1
    python benchmarks/cartpole_remedies.py --quick            # smoke test
    python benchmarks/cartpole_remedies.py --only "LSTD PL" "LSTD PL iwcv"
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
import warnings
from pathlib import Path

import gymnasium as gym
import torch
from torchrl.envs import GymWrapper, ObservationNorm, TransformedEnv

from torch_api import ActivePolicyIteration, GaussianActionBasis, RunSpec
from torch_api.collection import collect_episodes
from torch_api.core.quadratic_basis import QuadraticActionBasis
from torch_api.data import REWARD_KEY
from torch_api.policies import LinearQPolicy

OBS_SCALE = (2.4, 2.0, 0.21, 2.0)  # (m, m/s, rad, rad/s): normalised observation = s / scale
GOOD = 475  # a greedy return at least this is "balanced" (of TEST_STEPS)
TEST_STEPS = 500  # CartPole-v1's own cap
FIRST_80 = (80,) + (5,) * 7  # a first iteration of 80 episodes of pi_1 (uniform), then 5
FIRST_120 = (120,) + (4,) * 7  # the showcase's default since 2026-12-07: 120, then 4
FIRST_120_3 = (120,) + (3,) * 9  # the same first batch, then 9 iterations of 3
FIRST_120_2 = (120,) + (2,) * 14  # ... then 14 iterations of 2
BASE = {"fit": "lstd", "schedule": (5,) * 6, "lam": 1e-3, "flattening": 1.0, "active": False}
REMEDIES = {  # name: what differs from BASE
    "LSTD PL": {},
    "BRM PL": {"fit": "brm"},
    "BRM AL": {"fit": "brm", "active": True},
    "LSTD AL": {"active": True},
    "LSTD PL iwcv": {"flattening": "iwcv"},
    "LSTD PL ν=0.5": {"flattening": 0.5},
    "BRM PL iwcv": {"fit": "brm", "flattening": "iwcv"},
    "LSTD AL iwcv": {"active": True, "flattening": "iwcv"},
    "LSTD PL λ=0.1": {"lam": 0.1},
    "LSTD PL 10 episodes": {"schedule": (10,) * 6},
    "LSTD PL ε=0.15 fixed": {"epsilon_decay": "constant"},
    "LSTD PL softmax β=0.5": {"improvement": "softmax", "beta": 0.5},
    "LSTD PL ν=0": {"flattening": 0.0},
    "LSTD PL iwcv, 10 episodes": {"flattening": "iwcv", "schedule": (10,) * 6},
    "LSTD PL iwcv, ε=0.15 fixed": {"flattening": "iwcv", "epsilon_decay": "constant"},
    # the showcase's remedies (examples/torchrl_pipeline.py; run with --iterations 8)
    "LSTD PL ν=0 quadratic": {"flattening": 0.0, "basis": "quadratic"},
    "LSTD PL ν=0, M_1=80": {"flattening": 0.0, "schedule": FIRST_80},
    "LSTD PL ν=0 quadratic, M_1=80": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_80,
    },
    "LSTD AL ν=0 quadratic, M_1=80": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_80, "active": True,
    },
    "LSTD PL ν=1 quadratic, M_1=80": {"basis": "quadratic", "schedule": FIRST_80},
    "LSTD PL iwcv quadratic, M_1=80": {
        "flattening": "iwcv", "basis": "quadratic", "schedule": FIRST_80,
    },
    "BRM PL ν=0 quadratic, M_1=80": {
        "fit": "brm", "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_80,
    },
    # against the cart leaving the track (docs/cartpole_remedies.md)
    "LSTD PL ν=0 quadratic, M_1=80, γ=0.99": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_80, "gamma": 0.99,
    },
    "LSTD PL ν=0 quadratic, M_1=80, γ=0.99, λ=1e-5": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_80, "gamma": 0.99,
        "lam": 1e-5,
    },
    "LSTD PL ν=0 quadratic, M_1=80, softmax β=0.1": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_80,
        "improvement": "softmax", "beta": 0.1,
    },
    "LSTD PL ν=0 quadratic, M_1=120, 7 × 4": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_120,
    },
    "LSTD PL ν=0 quadratic, M_1=120, 7 × 4, softmax β=0.1": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_120,
        "improvement": "softmax", "beta": 0.1,
    },
    "LSTD PL ν=0 quadratic, M_1=120, 9 × 3": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_120_3,
    },
    "LSTD PL ν=0 quadratic, M_1=120, 14 × 2": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_120_2,
    },
    "LSTD AL ν=0 quadratic, M_1=120, 7 × 4": {
        "flattening": 0.0, "basis": "quadratic", "schedule": FIRST_120, "active": True,
    },
}  # fmt: skip


def make_env(rows: int) -> TransformedEnv:
    """``rows`` CartPoles as one TorchRL env ``[rows]``, one-hot actions, unit-scale states."""
    vector = gym.vector.SyncVectorEnv(
        [lambda: gym.make("CartPole-v1")] * rows, autoreset_mode=gym.vector.AutoresetMode.DISABLED
    )
    norm = ObservationNorm(
        loc=torch.zeros(4), scale=torch.tensor(OBS_SCALE), in_keys=["observation"],
        standard_normal=True,
    )  # fmt: skip
    return TransformedEnv(GymWrapper(vector), norm)


def make_basis(kind: str = "grid") -> GaussianActionBasis:
    if kind == "quadratic":  # [1, s, s_i s_j] per action (the showcase's)
        return QuadraticActionBasis(obs_dim=4, num_actions=2)
    centers = torch.tensor(list(itertools.product((-1.0, 0.0, 1.0), repeat=4)))  # [81, 4]
    return GaussianActionBasis(centers=centers, tau=1.0, num_actions=2)


def make_evaluator(trials: int, episodes: int):
    env = make_env(trials * episodes)

    def evaluate(policy: LinearQPolicy, seed: int) -> dict:
        env.set_seed(int(seed))
        greedy = LinearQPolicy(
            basis=policy.basis, theta=policy.theta, epsilon=0.0, tie_break=policy.tie_break
        )
        test = collect_episodes(
            env, greedy, num_episodes=episodes, num_steps=TEST_STEPS, rewarded=True
        )
        steps = (test[REWARD_KEY] * test["mask"]).sum(-1).double()  # steps until the first done
        return {"greedy_return": steps.mean(-1).tolist()}  # [T]

    return evaluate


def run(name: str, args) -> dict:
    setting = BASE | REMEDIES[name]
    options = {}
    if setting.get("epsilon_decay"):  # ε_l = 0.15 in every iteration: no jump towards greedy
        options["epsilon_decay"] = setting["epsilon_decay"]
    if setting.get("improvement"):
        options |= {"improvement": setting["improvement"], "beta": setting["beta"]}
    if setting["active"]:
        options["num_repeats"] = args.repeats
    schedule = setting["schedule"][: args.iterations]
    spec = RunSpec.of(
        schedule=schedule,
        num_steps=args.steps,
        gamma=setting.get("gamma", 0.95),
        mode="active" if setting["active"] else "passive",
        lam=setting["lam"],
        psi_mode="single",
        fit=setting["fit"],
        flattening=setting["flattening"],
        num_trials=args.trials,
        trial_seeds=list(range(args.first_seed, args.first_seed + args.trials)),
        keep_reward_free=False,
        **options,
    )
    api = ActivePolicyIteration(
        spec,
        env=make_env,
        basis=make_basis(setting.get("basis", "grid")),
        evaluate=make_evaluator(args.trials, args.test_episodes),
    )
    started = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # collapsed weights: the ESS column
        history = api.run()
    api.close()
    returns = torch.tensor([r.performance["greedy_return"] for r in history])  # [L, T]
    best = returns.max(0).values
    last = history[-1]
    bought = torch.tensor(last.rewarded_transitions, dtype=torch.float64)  # each trial's own
    ess = torch.tensor(last.effective_sample_size) / bought
    chosen = torch.tensor([r.chosen for r in history])  # [L, T]: 0 is pi_l itself
    return {
        "name": name,
        "mean_return": returns.mean(1).tolist(),
        "last_return": returns[-1].tolist(),  # per trial (a paired test of two rows)
        "final_good": int((returns[-1] >= GOOD).sum()),
        "lost": int(((best >= GOOD) & (returns[-1] < GOOD)).sum()),
        "nu": float(torch.tensor(last.flattening).mean()),
        "ess_percent": float(100 * ess.mean()),
        "other_than_pi_l": float((chosen != 0).double().mean()) if setting["active"] else None,
        "rewarded_transitions": round(float(bought.mean())),  # mean over trials
        "seconds": time.perf_counter() - started,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--first-seed", type=int, default=0, help="trial seeds from this one")
    parser.add_argument("--iterations", type=int, default=6)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=2, help="Z of the active runs")
    parser.add_argument("--test-episodes", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--only", nargs="*", choices=list(REMEDIES), default=None)
    parser.add_argument("--quick", action="store_true", help="2 trials, 2 iterations, 20 steps")
    parser.add_argument("--out", default="results/cartpole_remedies.json")
    args = parser.parse_args()
    if args.quick:
        args.trials, args.iterations, args.steps, args.test_episodes = 2, 2, 20, 1
        args.only = args.only or ["LSTD PL", "BRM AL", "LSTD PL iwcv"]
    torch.set_num_threads(args.threads)
    rows = []
    print(
        f"| remedy | greedy return, l = 1…{args.iterations} (mean of {args.trials} trials) "
        f"| ≥ {GOOD} at the end | lost | ν at the end | ESS % | AL: share not pi_l "
        "| rewarded transitions | s |"
    )
    print("|" + " --- |" * 9)
    for name in args.only or REMEDIES:
        row = run(name, args)
        rows.append(row)
        curve = " ".join(f"{v:.0f}" for v in row["mean_return"])
        share = "-" if row["other_than_pi_l"] is None else f"{row['other_than_pi_l']:.2f}"
        print(
            f"| {name} | {curve} | {row['final_good']}/{args.trials} | {row['lost']} | "
            f"{row['nu']:.2f} | {row['ess_percent']:.1f} | {share} | "
            f"{row['rewarded_transitions']} | "
            f"{row['seconds']:.0f} |",
            flush=True,
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
