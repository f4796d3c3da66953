"""How far the paper's batting basis lets least-squares policy iteration go (its ceiling).

Two measurements, both on ``BattingEnv`` with the paper's basis (54 Gaussian centres, τ = 3π/2,
B = 110), psi_hat of the single transition, λ = 1e-3, γ = 1:

1. **LSPI on abundant random data.** ``M`` uniformly random episodes (M = 200, 1000, 3000),
   collected once; then ``--iterations`` rounds of the library's policy evaluation (the design
   of eq. 20-28 with per-decision importance weights towards pi_l) and improvement, pi_l the
   ε-greedy policy of θ_{l-1} with ε_l = 0.15 / l, θ_0 = 1 (pi_1 uniform). After every round
   the score of pi_{l+1} is measured as in Figure 10 (eq. 68): Σ carry over 20 test episodes,
   here the mean over ``--test-episodes`` episodes times 20. No reward budget limits this
   learner, so its best score is the most the basis lets policy iteration reach.
2. **Evaluation capacity.** A near-optimal closed-loop rule (cock until the elbow is cocked,
   then swing) samples ``--capacity-episodes`` episodes with ε = ``--capacity-epsilon``; the
   basis evaluates that rule from its own data (on-policy, weights 1) and the greedy policy of
   the fitted Q̂ is scored ("greedy once"). A basis that can hold the optimum gives the rule's
   score back.

Reference: the best of the 1024 open-loop action sequences without noise
(``examples/batting_reference.py``), scored with noise like every policy here, and its
noiseless carry × 20.

    python benchmarks/batting_ceiling.py               # ~10 min on 2 cores
    python benchmarks/batting_ceiling.py --quick       # a smoke test
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
from batting_reference import reference_optimum  # noqa: E402

from envs.batting import BASIS_TAU, MAX_STEPS, N_ACTIONS, BattingEnv, basis_centers  # noqa: E402
from torch_api.collection import collect_episodes  # noqa: E402
from torch_api.core.basis import GaussianActionBasis  # noqa: E402
from torch_api.core.design import build_design  # noqa: E402
from torch_api.core.psi import PsiHat  # noqa: E402
from torch_api.core.solve import DEFAULT_LAMBDA, weighted_ridge  # noqa: E402
from torch_api.data import REWARD_KEY  # noqa: E402
from torch_api.policies import ActionProbsPolicy, LinearQPolicy, sample_actions  # noqa: E402

TEST_EPISODES_PER_SCORE = 20  # eq. 68: a score is Σ carry over 20 test episodes
COCKED_ELBOW = -0.7  # (rad) the rule swings once the elbow φ2 is below this (limit: -π/4)
WHIPPING_ELBOW = 2.0  # (rad/s) ... or while the elbow swings forward faster than this


class SequencePolicy(ActionProbsPolicy):
    """An open-loop action sequence (ε-soft), indexed by the env's ``step_count``."""

    def __init__(self, *, sequence, epsilon: float = 0.0, **io) -> None:
        super().__init__(num_actions=N_ACTIONS, **io)
        self.sequence = torch.as_tensor(sequence, dtype=torch.long)
        self.epsilon = float(epsilon)
        self.in_keys = [self.observation_key, "step_count"]

    def forward(self, tensordict):
        step = tensordict.get("step_count").squeeze(-1).clamp(max=len(self.sequence) - 1)
        greedy = torch.nn.functional.one_hot(self.sequence[step], N_ACTIONS).to(torch.float64)
        probs = (1.0 - self.epsilon) * greedy + self.epsilon / N_ACTIONS
        tensordict.set(self.action_key, sample_actions(probs, self.streams))
        tensordict.set(self.probs_key, probs)
        return tensordict


class CockThenSwing(ActionProbsPolicy):
    """A near-optimal closed-loop rule: cock (action 0) until the elbow is cocked, then swing.

    Swings when the elbow is cocked (φ2 < ``COCKED_ELBOW``) or already whipping forward
    (φ̇2 > ``WHIPPING_ELBOW``): the state-feedback form of the best open-loop sequence (cock
    twice, then swing). Chosen from a small grid (scores 136-259); ε-soft.
    """

    def __init__(self, *, epsilon: float = 0.0, **io) -> None:
        super().__init__(num_actions=N_ACTIONS, **io)
        self.epsilon = float(epsilon)

    def _action_probs(self, obs: torch.Tensor) -> torch.Tensor:
        obs = obs.to(torch.float64)
        swing = (obs[..., 2] < COCKED_ELBOW) | (obs[..., 3] > WHIPPING_ELBOW)
        greedy = torch.nn.functional.one_hot(swing.long(), N_ACTIONS).to(torch.float64)
        return (1.0 - self.epsilon) * greedy + self.epsilon / N_ACTIONS


def collect(policy, episodes: int, seed: int, end_at_hit: bool = False) -> object:
    env = BattingEnv(batch_size=episodes, seed=seed, end_at_hit=end_at_hit)
    policy = policy.with_streams(torch.Generator().manual_seed(seed + 1))
    return collect_episodes(env, policy, num_episodes=episodes, num_steps=MAX_STEPS, rewarded=True)


def score(policy, episodes: int, seed: int) -> tuple[float, float]:
    """Score of eq. 68 (20 × mean return per episode) and its standard error, over episodes."""
    data = collect(policy, episodes, seed)
    ret = (data[REWARD_KEY] * data["mask"]).sum(-1).double()
    se = ret.std() / math.sqrt(episodes)
    return float(TEST_EPISODES_PER_SCORE * ret.mean()), float(TEST_EPISODES_PER_SCORE * se)


def fit(episodes, policy, psi: PsiHat, lam: float, method: str = "brm") -> torch.Tensor:
    """θ of the library's fit (``"brm"``: ridge regression of r on psi_hat, eq. 22-28) or of
    LSTD-Q (``"lstd"``: ``θ = (Φᵀ W (Φ − γΦ') / n + λI)⁻¹ Φᵀ W r / n``, Φ − γΦ' = psi_hat)."""
    design = build_design(episodes, policy, psi, min_ess_fraction=0.0)
    if method == "brm":
        return weighted_ridge(
            design.x, design.w, design.reward, lam, num_samples=design.num_samples
        )
    obs = episodes["observation"].reshape(-1, episodes["observation"].shape[-1])
    phi = psi.basis.phi(obs.to(torch.float64), episodes["action"].reshape(-1))
    weighted = phi * (design.w * design.mask)[:, None] / design.num_samples
    a = weighted.T @ design.x
    b = weighted.T @ design.reward
    return torch.linalg.solve(a + lam * torch.eye(a.shape[0], dtype=a.dtype), b)


def lspi_on_random_data(args, num_episodes: int, basis, psi) -> dict:
    """LSPI rounds on ``num_episodes`` uniformly random episodes; scores of pi_{l+1}."""
    started = time.perf_counter()
    uniform = LinearQPolicy(basis=basis, theta=torch.zeros(basis.num_features), epsilon=1.0)
    data = collect(uniform, num_episodes, args.seed, args.end_at_hit)
    theta = torch.ones(basis.num_features, dtype=torch.float64)
    rounds = []
    for l_now in range(1, args.iterations + 1):
        pi_l = LinearQPolicy(basis=basis, theta=theta, epsilon=0.15 / l_now)
        theta = fit(data, pi_l, psi, args.lam, args.fit)
        test_seed = args.seed + 1000 * l_now + 7
        s, se = score(
            LinearQPolicy(basis=basis, theta=theta, epsilon=0.15 / (l_now + 1)),
            args.test_episodes,
            test_seed,
        )
        g, gse = score(
            LinearQPolicy(basis=basis, theta=theta, epsilon=0.0), args.test_episodes, test_seed
        )
        rounds.append({"iteration": l_now, "score": s, "se": se, "greedy": g, "greedy_se": gse})
    return {"episodes": num_episodes, "rounds": rounds, "seconds": time.perf_counter() - started}


def evaluation_capacity(args, basis, psi) -> dict:
    """Fit Q̂ of the ε-soft rule from its own episodes; score the rule and Q̂'s greedy policy."""
    rule = CockThenSwing(epsilon=args.capacity_epsilon)
    data = collect(rule, args.capacity_episodes, args.seed + 5, args.end_at_hit)
    # psi_hat and the weights need the evaluation policy's probabilities: the rule itself
    theta = fit(data, rule, psi, args.lam, args.fit)
    seed = args.seed + 99
    return {
        "rule": score(CockThenSwing(epsilon=0.0), args.test_episodes, seed),
        "rule_soft": score(rule, args.test_episodes, seed),
        "greedy_of_fit": score(
            LinearQPolicy(basis=basis, theta=theta, epsilon=0.0), args.test_episodes, seed
        ),
    }


def print_capacity(args, cap: dict, optimum: float) -> None:
    print(
        f"\nevaluation capacity: the rule (swing iff φ2 < {COCKED_ELBOW} or "
        f"φ̇2 > {WHIPPING_ELBOW}), "
        f"{args.capacity_episodes} episodes at ε = {args.capacity_epsilon}, fitted once\n"
    )
    print("| policy | score | % of optimum |")
    print("|---|---:|---:|")
    for name, key in (
        ("the rule, greedy", "rule"),
        (f"the rule, ε = {args.capacity_epsilon}", "rule_soft"),
        ("greedy policy of the fitted Q̂", "greedy_of_fit"),
    ):
        s, se = cap[key]
        print(f"| {name} | {s:.1f} ± {se:.1f} | {100 * s / optimum:.0f} % |")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, nargs="+", default=[200, 1000, 3000])
    parser.add_argument("--iterations", type=int, default=8)
    parser.add_argument("--test-episodes", type=int, default=500)
    parser.add_argument("--capacity-episodes", type=int, default=1000)
    parser.add_argument("--capacity-epsilon", type=float, default=0.15)
    parser.add_argument("--lam", type=float, default=DEFAULT_LAMBDA)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--basis-widths",
        type=float,
        nargs=4,
        default=None,
        metavar="W",
        help="beyond the paper: kernel widths per state dimension w1 w2 w3 w4 (default: the "
        "paper's τ = 3π/2 for all)",
    )
    parser.add_argument(
        "--end-at-hit", action="store_true", help="beyond the paper: episodes end at the hit"
    )
    parser.add_argument(
        "--fit", choices=("brm", "lstd"), default="brm", help="the library's fit or LSTD-Q"
    )
    parser.add_argument("--no-capacity", action="store_true", help="skip the capacity check")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test)")
    parser.add_argument("--out", default="", help="write the results as JSON here")
    args = parser.parse_args(argv)
    if args.quick:
        args.episodes, args.iterations, args.test_episodes = [20], 2, 20
        args.capacity_episodes = 20
    if min(args.episodes) < 1 or args.iterations < 1 or args.test_episodes < 2:
        parser.error("--episodes and --iterations must be >= 1, --test-episodes >= 2")
    torch.set_num_threads(1)
    started = time.perf_counter()
    try:
        basis = GaussianActionBasis(
            centers=basis_centers(),
            tau=BASIS_TAU if args.basis_widths is None else 1.0,
            widths=args.basis_widths,
            num_actions=N_ACTIONS,
        )
    except ValueError as error:
        parser.error(str(error))
    psi = PsiHat(basis=basis, gamma=1.0, mode="single")

    best = reference_optimum()
    optimum_noiseless = TEST_EPISODES_PER_SCORE * best["best_carry"]
    optimum, optimum_se = score(
        SequencePolicy(sequence=best["best_sequence"]), args.test_episodes, args.seed + 3
    )
    seq = "".join(map(str, best["best_sequence"]))
    print(
        f"reference optimum: open-loop {seq}, noiseless {optimum_noiseless:.1f}, "
        f"with noise {optimum:.1f} ± {optimum_se:.1f} (score of eq. 68, Σ carry over 20 "
        f"episodes)\n"
    )

    runs = [lspi_on_random_data(args, m, basis, psi) for m in args.episodes]
    head = " | ".join(f"l = {r['iteration']}" for r in runs[0]["rounds"])
    print(
        f"LSPI, paper basis, uniformly random data: score of pi_{{l+1}} (ε = 0.15/(l+1)), "
        f"mean ± s.e. over {args.test_episodes} test episodes × 20\n"
    )
    print(f"| random episodes | {head} | best | best / optimum |")
    print("|---:|" + "---:|" * (len(runs[0]["rounds"]) + 2))
    for run in runs:
        cells = " | ".join(f"{r['score']:.1f} ± {r['se']:.1f}" for r in run["rounds"])
        top = max(r["score"] for r in run["rounds"])
        run["best"] = top
        print(f"| {run['episodes']} | {cells} | {top:.1f} | {100 * top / optimum:.0f} % |")
    print("\ngreedy policy of the same θ_l:\n")
    print(f"| random episodes | {head} |")
    print("|---:|" + "---:|" * len(runs[0]["rounds"]))
    for run in runs:
        cells = " | ".join(f"{r['greedy']:.1f}" for r in run["rounds"])
        print(f"| {run['episodes']} | {cells} |")

    cap = None if args.no_capacity else evaluation_capacity(args, basis, psi)
    if cap is not None:
        print_capacity(args, cap, optimum)
    ceiling = max(run["best"] for run in runs)
    wall = time.perf_counter() - started
    print(
        f"\nceiling (best LSPI score above): {ceiling:.1f} = {100 * ceiling / optimum:.0f} % of "
        f"the optimum {optimum:.1f}; wall {wall:.0f} s"
    )
    result = {
        "args": vars(args),
        "optimum": {
            "sequence": best["best_sequence"],
            "noiseless": optimum_noiseless,
            "score": optimum,
            "se": optimum_se,
        },
        "lspi": runs,
        "capacity": cap,
        "ceiling": ceiling,
        "wall_seconds": wall,
    }
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
