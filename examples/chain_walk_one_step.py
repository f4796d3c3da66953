"""One-step sampling-policy selection on the 10-state chain walk (paper section 3.5, Figs. 3-5).

For three evaluation policies (ε = 0.1 versions of 'RRRRRRRRRR', 'RLLLLLRRRR', 'LLLLLRRRRR')
and ten sampling-policy candidates (ε = k/10), every trial

1. collects Z = 5 reward-free sets of M = 10 episodes per candidate and computes J' (Algorithm 2),
2. collects a rewarded set of M episodes per candidate, fits θ_k (eq. 22-28) and measures its
   true generalisation error Ḡ_k exactly from the model (docs/chain_walk.md),
3. records Ḡ of the candidate chosen by active learning (AL: argmin J'), by passive learning
   (PL: k = 1, the evaluation policy itself) and by an oracle (OPT: argmin Ḡ).

All trials run as one batch: the environment holds T·Z·K·M chains at once.

    python examples/chain_walk_one_step.py --trials 100

``--device cuda`` runs all of it on the GPU (the walks' random numbers are drawn on the CPU and
moved, so a seed gives the same episodes on either device).
"""

from __future__ import annotations

from dataclasses import dataclass

from _cli import SelectionOptions, ThreadOptions, field, not_here, parse
from _process import collector_off_for_imports, configure_process, freeze_imported_objects


@dataclass
class Args(SelectionOptions, ThreadOptions):
    """Command-line arguments of the one-step experiment."""

    trials: int = field(100, low=1, help="independent trials (the paper: 100)")
    seed: int = field(0, low=0, help="seed of the environment and the policies")
    candidates: int = field(10, low=2, help="K, candidate k samples with ε = k / K")
    eval_epsilon: float = field(0.1, low=0.0, high=1.0, help="ε of the evaluation policies")
    episodes: int = field(10, low=1, help="M, episodes per data set")
    steps: int = field(10, low=1, help="N, steps per episode")
    out_dir: str = field("results/chain_walk_one_step", help="where the JSON and the figures go")
    device: str = field(
        "cpu", help="where the chain walks, the rollouts and the algebra run (cpu, cuda or cuda:N)"
    )


def parse_args(argv=None) -> Args:
    return parse(Args, argv, __doc__, unavailable=not_here("resume", "backend", "logger"))


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below
    collector_off_for_imports()  # examples/_process.py: start-up and exit cost less

import dataclasses
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import scipy.stats
import torch
from tqdm import tqdm

from counter_rng import CounterStreams, derive_keys
from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv, deterministic_policy_probs
from envs.chain_walk.exact import exact_psi, state_action_occupancy, true_generalisation_error
from torch_api.collection import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.design import build_design
from torch_api.core.psi import PsiHat
from torch_api.core.solve import weighted_ridge
from torch_api.loop.selector import j_values
from torch_api.policies import TabularPolicy
from torch_api.streams import trial_seeds_of

BASE_POLICIES = ("RRRRRRRRRR", "RLLLLLRRRR", "LLLLLRRRRR")  # eq. 51-53, 10-letter readings
# the roles of a trial's streams: reward-free walks and sampling, rewarded walks and sampling
_ROLE_FREE_ENV, _ROLE_FREE_POLICY, _ROLE_REWARDED_ENV, _ROLE_REWARDED_POLICY = 1, 2, 3, 4


def state_index(obs: torch.Tensor) -> torch.Tensor:
    """Chain-walk observation (the state number 1..10) -> table row 0..9."""
    return obs[..., 0].round().long() - 1


def row_tables(tables: torch.Tensor, lead: tuple[int, ...]) -> torch.Tensor:
    """Probability table of every environment row: ``[K, S, A]`` -> ``[prod(lead)·K·M, S, A]``.

    ``lead`` is the shape ``(..., K, M)`` of the environment batch, K at position -2.
    """
    shape = [1] * len(lead) + list(tables.shape[-2:])
    shape[-4] = tables.shape[0]
    return tables.reshape(shape).expand(*lead, *tables.shape[-2:]).reshape(-1, *tables.shape[-2:])


def run_policy(args: Args, base: str, seed: int) -> dict:
    """All trials for one evaluation policy; returns J' and Ḡ ``[T, K]`` (on the CPU).

    Everything else lives on ``args.device``: the walks, the policies' tables and the algebra.
    Trial t has the key ``trial_seeds_of(seed, [t])``; its walks and its samplers draw from
    streams derived from it (one role each), so trial t's numbers are those of a run of trial t
    alone, whatever ``--trials`` is.
    """
    t, z, k, m, n = args.trials, args.repeats, args.candidates, args.episodes, args.steps
    device = torch.device(args.device)
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS).unsqueeze(-1), tau=TAU, num_actions=2)
    psi = PsiHat(basis=basis, gamma=GAMMA, mode="grouped")
    eval_table = deterministic_policy_probs(base, args.eval_epsilon).to(device)
    evaluation = TabularPolicy(table=eval_table, state_index=state_index)
    eps = torch.arange(1, k + 1, dtype=torch.float64) / k
    cand_tables = deterministic_policy_probs(base, eps).to(device)  # [K, S, A]

    keys = torch.tensor(trial_seeds_of(seed, range(t)))  # one key per trial

    def streams(role: int) -> CounterStreams:  # one stream per trial of one role
        return CounterStreams(derive_keys(keys, role))

    # Reward-free data: [T, Z, K, M] chains, candidate k on its rows (Algorithm 2, steps 2-5).
    env = ChainWalkEnv(batch_size=t * z * k * m, device=device)
    env.set_block_seeds(derive_keys(keys, _ROLE_FREE_ENV))
    sampler = TabularPolicy(
        table=row_tables(cand_tables, (t, z, k, m)),
        state_index=state_index,
        streams=streams(_ROLE_FREE_POLICY),
    )
    # one table per environment row: the policy's "trials" are the rows, one episode each
    free = collect_episodes(env, sampler, num_episodes=1, num_steps=n, rewarded=False)
    j_all = j_values(free.reshape(t, z, k, m, n), None, evaluation, psi, args.lam)  # [T, Z, K]
    j_prime = j_all.mean(1)

    # Rewarded data: one fresh set of M episodes per trial and candidate; θ_k and its Ḡ_k.
    env = ChainWalkEnv(batch_size=t * k * m, device=device)
    env.set_block_seeds(derive_keys(keys, _ROLE_REWARDED_ENV))
    sampler = TabularPolicy(
        table=row_tables(cand_tables, (t, k, m)),
        state_index=state_index,
        streams=streams(_ROLE_REWARDED_POLICY),
    )
    bought = collect_episodes(env, sampler, num_episodes=1, num_steps=n, rewarded=True)
    design = build_design(bought.reshape(t, k, m, n), evaluation, psi)
    theta = weighted_ridge(design.x, design.w, design.reward, args.lam)  # [T, K, B]

    model = env.model()
    states = torch.arange(1, model.n_states + 1, dtype=torch.float64, device=device)[:, None]
    phi_all = basis.phi_all(states)  # [S, A, B]
    psi_true = exact_psi(model.transitions, phi_all, eval_table, GAMMA)
    occupancy = state_action_occupancy(model.transitions, eval_table, model.initial, n)
    g_true = true_generalisation_error(theta, psi_true, model.expected_reward, occupancy)
    return {"j_prime": j_prime.cpu(), "g_true": g_true.cpu()}


def summarise(j_prime: torch.Tensor, g_true: torch.Tensor) -> dict:
    """AL / PL / OPT choices and the table's numbers for one evaluation policy."""
    trials = torch.arange(j_prime.shape[0])
    al = g_true[trials, j_prime.argmin(-1)]
    pl = g_true[:, 0]
    opt = g_true.min(-1).values
    rho = scipy.stats.spearmanr(j_prime.mean(0).numpy(), g_true.mean(0).numpy()).statistic
    return {
        "g_al": al.tolist(),
        "g_pl": pl.tolist(),
        "g_opt": opt.tolist(),
        "al_choice": (j_prime.argmin(-1) + 1).tolist(),
        "mean_g_al": al.mean().item(),
        "mean_g_pl": pl.mean().item(),
        "mean_g_opt": opt.mean().item(),
        "share_al_at_least_as_good_as_pl": (al <= pl).double().mean().item(),
        "spearman_mean_j_vs_mean_g": float(rho),
    }


METHOD_COLOURS = {"AL": "tab:red", "PL": "tab:blue", "OPT": "tab:green"}  # as in every figure


def mean_se_clipped(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over trials (axis 0) and its ± 1 s.e. bars ``[2, K]``, the lower bar clipped at 0.

    The errors here are sums of squares: never negative, so no bar is drawn below zero.
    """
    mean = values.mean(0)
    se = values.std(0, ddof=1) / np.sqrt(values.shape[0]) if values.shape[0] > 1 else 0 * mean
    return mean, np.stack([np.minimum(se, mean), se])


def save(fig, title: str, path: Path) -> None:
    """Title the figure, lay it out, write it (120 dpi) and close it."""
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_profiles(results: dict, key: str, ylabel: str, path: Path, obtained: bool) -> None:
    """Mean ± 1 s.e. over trials of a [T, K] error over the candidates k (Figures 3 and 4).

    With ``obtained``, the mean Ḡ that AL, PL and OPT obtain is drawn across each panel.
    """
    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(4.3 * n, 3.6), squeeze=False)
    for ax, (base, res) in zip(axes[0], results.items(), strict=True):
        values = np.asarray(res[key])
        trials, k = values.shape
        ks = np.arange(1, k + 1)
        mean, bars = mean_se_clipped(values)
        style = {"color": "0.2", "marker": "o", "ms": 4, "capsize": 3}
        ax.errorbar(ks, mean, yerr=bars, label="mean ± s.e. over trials", **style)
        if obtained:
            for name, dash in (("al", "--"), ("pl", ":"), ("opt", "-.")):
                label = name.upper()
                level = res["summary"][f"mean_g_{name}"]
                colour = METHOD_COLOURS[label]
                ax.axhline(level, color=colour, ls=dash, lw=1.5, label=f"mean Ḡ {label} obtains")
        ax.set_title(f"evaluation policy {base}", fontsize=9)
        ax.set_xlabel(f"candidate k (ε = k/{k})")
        ax.set_ylabel(ylabel)
        ax.set_xticks(ks)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="upper left")
    title = f"{ylabel}: mean over T = {trials} trials, bars ± 1 standard error of the mean "
    save(fig, title + "(clipped at 0)", path)


def plot_boxes(results: dict, path: Path) -> None:
    """Ḡ obtained by AL, PL and OPT per trial as box plots (Figure 5)."""
    n = len(results)
    fig, axes = plt.subplots(1, n, figsize=(4.3 * n, 3.8), squeeze=False)
    names = ("AL", "PL", "OPT")
    for ax, (base, res) in zip(axes[0], results.items(), strict=True):
        data = [res["summary"][f"g_{name.lower()}"] for name in names]
        boxes = ax.boxplot(
            data,
            whis=(5, 95),
            showfliers=False,
            showmeans=True,
            patch_artist=True,
            medianprops={"color": "black"},
            meanprops={"marker": "D", "markerfacecolor": "white", "markeredgecolor": "black"},
        )
        for box, name in zip(boxes["boxes"], names, strict=True):
            box.set_facecolor(METHOD_COLOURS[name])
            box.set_alpha(0.6)
        ax.set_xticks([1, 2, 3], list(names))
        ax.set_title(f"evaluation policy {base}", fontsize=9)
        ax.set_ylabel("true generalisation error Ḡ obtained")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3, axis="y")
    trials = len(data[0])
    title = f"Ḡ obtained over T = {trials} trials: box = quartiles, line = median, "
    save(fig, title + "◇ = mean, whiskers = 5 % and 95 % quantiles", path)


def main(argv=None) -> dict:
    args = parse_args(argv)
    configure_process(args)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    results = {}
    for i, base in enumerate(tqdm(BASE_POLICIES, desc="evaluation policies")):
        res = run_policy(args, base, seed=args.seed * 1000 + 10 * i)
        results[base] = {
            "j_prime": res["j_prime"].tolist(),
            "g_true": res["g_true"].tolist(),
            "summary": summarise(res["j_prime"], res["g_true"]),
        }
    wall = time.perf_counter() - started

    header = (
        f"{'evaluation policy':<18} {'AL':>9} {'PL':>9} {'OPT':>9} {'AL<=PL':>7} {'rho(J,G)':>9}"
    )
    print(f"\nOne-step experiment: {args.trials} trials, mean Ḡ obtained ({wall:.1f} s)")
    print(header)
    for base, res in results.items():
        s = res["summary"]
        print(
            f"{base:<18} {s['mean_g_al']:9.5f} {s['mean_g_pl']:9.5f} {s['mean_g_opt']:9.5f} "
            f"{s['share_al_at_least_as_good_as_pl']:7.2f} {s['spearman_mean_j_vs_mean_g']:9.3f}"
        )
    payload = {"args": dataclasses.asdict(args), "wall_seconds": wall, "results": results}
    (out / "one_step.json").write_text(json.dumps(payload))
    fig3 = out / "fig3_true_error.png"
    plot_profiles(results, "g_true", "true generalisation error Ḡ", fig3, obtained=True)
    fig4 = out / "fig4_j_estimate.png"
    plot_profiles(results, "j_prime", "reward-free estimate J'", fig4, obtained=False)
    plot_boxes(results, out / "fig5_obtained_error.png")
    print(f"wrote {out}/one_step.json and three figures")
    return payload


if __name__ == "__main__":
    freeze_imported_objects()
    main()
