"""One-step sampling-policy selection on the 10-state chain walk (paper section 3.5, Figs. 3-5).

For three evaluation policies (ε = 0.1 versions of 'RRRRRRRRRR', 'RLLLLLRRRR', 'LLLLLRRRRR')
and K = 10 sampling-policy candidates (ε = k/K), every trial computes J' of each candidate from
Z = 5 reward-free sets of M = 10 episodes (Algorithm 2), fits θ_k on a rewarded set of M
episodes per candidate (eq. 22-28), measures its true generalisation error Ḡ_k exactly, and
records Ḡ of the candidate chosen by AL (argmin J'), PL (k = 1, the evaluation policy) and an
oracle (OPT: argmin Ḡ). All trials run as one batch. Writes one_step.json and Figures 3-5:
``python examples/chain_walk_one_step.py --trials 100``.
"""

import json
import sys
import time
from dataclasses import asdict, dataclass
from math import inf
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import scipy.stats
import torch
import tyro

from counter_rng import CounterStreams, derive_keys
from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv, deterministic_policy_probs
from envs.chain_walk.exact import exact_psi, state_action_occupancy, true_generalisation_error
from torch_api import GaussianActionBasis, PsiHat, TabularPolicy, build_design
from torch_api.collection import collect_episodes
from torch_api.core.solve import weighted_ridge
from torch_api.loop.selector import j_values
from torch_api.streams import trial_seeds_of

BASE_POLICIES = ("RRRRRRRRRR", "RLLLLLRRRR", "LLLLLRRRRR")  # eq. 51-53, 10-letter readings
FREE_ENV, FREE_POLICY, REWARDED_ENV, REWARDED_POLICY = 1, 2, 3, 4  # roles of a trial's streams
COLOURS = {"AL": "tab:red", "PL": "tab:blue", "OPT": "tab:green"}


@dataclass
class Args:
    """Figures 3-5: one-step sampling-policy selection on the chain walk."""

    trials: int = 100
    """independent trials (the paper: 100)"""
    seed: int = 0
    """seed of the environments and the policies"""
    repeats: int = 5
    """Z, J-values averaged into J'"""
    lam: float = 1e-3
    """λ, ridge regularisation"""
    candidates: int = 10
    """K, candidate k samples with ε = k / K"""
    eval_epsilon: float = 0.1
    """ε of the evaluation policies"""
    episodes: int = 10
    """M, episodes per data set"""
    steps: int = 10
    """N, steps per episode"""
    out_dir: str = "results/chain_walk_one_step"
    """where the JSON and the figures go"""
    device: str = "cpu"
    """where the chain walks, the rollouts and the algebra run (cpu, cuda or cuda:N)"""
    threads: int = 1
    """torch intra-op threads (0: torch's default, one per core)"""


def state_index(obs: torch.Tensor) -> torch.Tensor:
    """Chain-walk observation (the state number 1..10) -> table row 0..9."""
    return obs[..., 0].round().long() - 1


def sampler(tables: torch.Tensor, lead: tuple[int, ...], keys, role: int) -> TabularPolicy:
    """Candidate k's table ``[K, S, A]`` on its rows of an env batch ``(T, ..., K, M)``."""
    shape = [1] * len(lead) + list(tables.shape[-2:])
    shape[-4] = tables.shape[0]
    rows = tables.reshape(shape).expand(*lead, *tables.shape[-2:]).reshape(-1, *shape[-2:])
    streams = CounterStreams(derive_keys(keys, role))
    return TabularPolicy(table=rows, state_index=state_index, streams=streams)


def run_policy(args: Args, base: str, seed: int) -> dict:
    """All trials for one evaluation policy: J' and Ḡ ``[T, K]`` (on the CPU)."""
    t, z, k, m, n = args.trials, args.repeats, args.candidates, args.episodes, args.steps
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2)
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="grouped")
    eval_table = deterministic_policy_probs(base, args.eval_epsilon).to(args.device)
    evaluation = TabularPolicy(table=eval_table, state_index=state_index)
    eps = torch.arange(1, k + 1, dtype=torch.float64) / k
    tables = deterministic_policy_probs(base, eps).to(args.device)  # [K, S, A]
    keys = torch.tensor(trial_seeds_of(seed, range(t)))  # one key per trial

    # Reward-free data: [T, Z, K, M] chains, candidate k on its rows (Algorithm 2, steps 2-5).
    env = ChainWalkEnv(batch_size=t * z * k * m, device=args.device)
    env.set_block_seeds(derive_keys(keys, FREE_ENV))
    policy = sampler(tables, (t, z, k, m), keys, FREE_POLICY)  # one episode a row
    free = collect_episodes(env, policy, num_episodes=1, num_steps=n, rewarded=False)
    j_prime = j_values(free.reshape(t, z, k, m, n), None, evaluation, psi, args.lam).mean(1)

    # Rewarded data: one fresh set of M episodes per trial and candidate; θ_k and its Ḡ_k.
    env = ChainWalkEnv(batch_size=t * k * m, device=args.device)
    env.set_block_seeds(derive_keys(keys, REWARDED_ENV))
    policy = sampler(tables, (t, k, m), keys, REWARDED_POLICY)
    bought = collect_episodes(env, policy, num_episodes=1, num_steps=n, rewarded=True)
    design = build_design(bought.reshape(t, k, m, n), evaluation, psi)
    theta = weighted_ridge(design.x, design.w, design.reward, args.lam)  # [T, K, B]

    model = env.model()
    states = torch.arange(1, model.n_states + 1, dtype=torch.float64, device=args.device)[:, None]
    psi_true = exact_psi(model.transitions, basis.phi_all(states), eval_table, GAMMA)
    occupancy = state_action_occupancy(model.transitions, eval_table, model.initial, n)
    g_true = true_generalisation_error(theta, psi_true, model.expected_reward, occupancy)
    return {"j_prime": j_prime.cpu(), "g_true": g_true.cpu()}


def summarise(j_prime: torch.Tensor, g_true: torch.Tensor) -> dict:
    """AL / PL / OPT choices and the table's numbers for one evaluation policy."""
    al, pl = g_true[torch.arange(len(j_prime)), j_prime.argmin(-1)], g_true[:, 0]
    opt = g_true.min(-1).values
    rho = scipy.stats.spearmanr(j_prime.mean(0).numpy(), g_true.mean(0).numpy()).statistic
    return {
        "g_al": al.tolist(), "g_pl": pl.tolist(), "g_opt": opt.tolist(),
        "al_choice": (j_prime.argmin(-1) + 1).tolist(), "mean_g_al": al.mean().item(),
        "mean_g_pl": pl.mean().item(), "mean_g_opt": opt.mean().item(),
        "share_al_at_least_as_good_as_pl": (al <= pl).double().mean().item(),
        "spearman_mean_j_vs_mean_g": float(rho),
    }  # fmt: skip


def plot(results: dict, path: Path, key: str | None, ylabel: str) -> None:
    """Per evaluation policy, mean ± s.e. over trials of a [T, K] error against k (Figures 3, 4)
    or, with ``key=None``, box plots of the Ḡ that AL, PL and OPT obtain (Figure 5)."""
    fig, axes = plt.subplots(1, len(results), figsize=(4.3 * len(results), 3.7), squeeze=False)
    for ax, (base, res) in zip(axes[0], results.items(), strict=True):
        s = res["summary"]
        if key is None:
            data = [s[f"g_{name.lower()}"] for name in COLOURS]
            ax.boxplot(data, whis=(5, 95), showfliers=False, showmeans=True)
            ax.set_xticks([1, 2, 3], list(COLOURS))
        else:
            values = np.asarray(res[key])
            ks, mean = np.arange(1, values.shape[1] + 1), values.mean(0)
            se = values.std(0, ddof=1) / np.sqrt(len(values)) if len(values) > 1 else 0 * mean
            bars = [np.minimum(se, mean), se]  # errors are never negative: bars clipped at 0
            ax.errorbar(ks, mean, yerr=bars, color="0.2", marker="o", ms=4, capsize=3)
            dashes = ("--", ":", "-.") if key == "g_true" else ()  # Figure 3: what each obtains
            for name, dash in zip(COLOURS, dashes, strict=False):
                label = f"mean Ḡ {name} obtains"
                ax.axhline(s[f"mean_g_{name.lower()}"], color=COLOURS[name], ls=dash, label=label)
            ax.set(xlabel=f"candidate k (ε = k/{len(ks)})", xticks=ks)
        ax.set(title=f"evaluation policy {base}", ylabel=ylabel, ylim=(0, None))
        ax.grid(alpha=0.3)
    if key == "g_true":
        axes[0][0].legend(fontsize=7, loc="upper left")
    what = "mean ± 1 s.e." if key else "box: quartiles, line: median, ▲: mean, whiskers: 5-95 %"
    fig.suptitle(f"{ylabel}: T = {len(s['g_al'])} trials, {what}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    limits = {"trials": (1, inf), "seed": (0, 2**63 // 1000 - 1), "repeats": (1, inf), "lam":
              (1e-10, inf), "candidates": (2, inf), "episodes": (1, inf), "steps": (1, inf),
              "eval_epsilon": (0.0, 1.0), "threads": (0, 1024)}  # fmt: skip
    for name, (low, high) in limits.items():
        if not low <= (value := getattr(args, name)) <= high:  # one line, exit 2
            print(f"error: {name} must lie in [{low}, {high}], got {value}", file=sys.stderr)
            raise SystemExit(2)
    try:
        (out := Path(args.out_dir)).mkdir(parents=True, exist_ok=True)
    except OSError as error:
        print(f"error: out_dir {args.out_dir!r} cannot be made: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    torch.set_num_threads(args.threads or torch.get_num_threads())
    started, results = time.perf_counter(), {}
    for i, base in enumerate(BASE_POLICIES):
        print(f"evaluation policy {base} ({i + 1}/{len(BASE_POLICIES)})", flush=True)
        res = run_policy(args, base, seed=args.seed * 1000 + 10 * i)
        results[base] = {**{k: v.tolist() for k, v in res.items()}, "summary": summarise(**res)}
    wall = time.perf_counter() - started
    print(f"\nOne-step experiment: {args.trials} trials, mean Ḡ obtained ({wall:.1f} s)")
    print(f"{'evaluation policy':<18} {'AL':>9} {'PL':>9} {'OPT':>9} {'AL<=PL':>7} {'rho(J,G)':>9}")
    for base, res in results.items():
        s = res["summary"]
        print(
            f"{base:<18} {s['mean_g_al']:9.5f} {s['mean_g_pl']:9.5f} {s['mean_g_opt']:9.5f} "
            f"{s['share_al_at_least_as_good_as_pl']:7.2f} {s['spearman_mean_j_vs_mean_g']:9.3f}"
        )
    payload = {"args": asdict(args), "wall_seconds": wall, "results": results}
    (out / "one_step.json").write_text(json.dumps(payload))
    plot(results, out / "fig3_true_error.png", "g_true", "true generalisation error Ḡ")
    plot(results, out / "fig4_j_estimate.png", "j_prime", "reward-free estimate J'")
    plot(results, out / "fig5_obtained_error.png", None, "true generalisation error Ḡ obtained")
    print(f"wrote {out}/one_step.json and three figures")
    return payload


if __name__ == "__main__":
    main()
