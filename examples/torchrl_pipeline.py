"""Active policy iteration inside a plain TorchRL pipeline: CartPole-v1 (or MountainCar-v0).

What a TorchRL user already has, used as it is: ``GymEnv(env_id)`` with its one-hot actions, an
``ObservationNorm`` (observations to unit scale) and a ``StepCounter`` (episodes of at most N
steps), batched by ``SerialEnv``; a ``Collector`` that buys the rewarded episodes; two
``TensorDictReplayBuffer``s of the user's own, one for reward-free and one for rewarded
episodes; and the user's own candidate sampling policy, a ``ProbabilisticActor`` (a hand-made
rule: push the way the pole falls, or the way the car moves).

What the library adds: :class:`~torch_api.loop.selector.SamplingPolicySelector` chooses, every
iteration of an active (AL) run, the candidate whose rewarded episodes should give the most
accurate value function, from reward-free episodes alone (the paper's J criterion, Algorithm
2); a passive (PL) run samples with pi_l itself. :func:`~torch_api.core.fit.fit_flattened` fits θ
on every rewarded episode so far (sample reuse: psi_hat and the per-decision importance
weights, flattened to ``w^ν``, then BRM or LSTD-Q); the ε-greedy policy of θ drives the next
iteration. After every iteration the greedy policy of θ runs in ``env.rollout`` under
``ExplorationType.DETERMINISTIC``: its return is the mean over the test episodes (CartPole:
steps until the pole falls, at most 500; MountainCar: minus the steps to the flag, -200 when
the car never gets there).

AL and PL run on the same seeds (paired: a pair's rewarded streams are the same, it differs by
the sampling policy), the paired t-test of the last greedy return is printed, and the greedy
return per iteration is drawn (``torchrl_pipeline.png``). Each environment has its own
defaults (``_pipeline_envs.DEFAULTS``; a flag at 0 or ``auto`` takes them):

    python examples/torchrl_pipeline.py                       # CartPole-v1, 5 seeds
    python examples/torchrl_pipeline.py --seeds 20            # the README's measured run
    python examples/torchrl_pipeline.py --env MountainCar-v0  # the example's earlier case

Durable, like every experiment example: each run (mode, seed) keeps what it buys in the
library's :class:`~torch_api.runs.store.RunStore` at ``<out-dir>/checkpoints/<mode>_seed<seed>.db``
— each iteration's selection (J', the reward-free episodes) before the rewarded episodes it
buys, those episodes before θ is fitted on them, θ and the iteration's row after. A folder
holding runs is refused unless ``--resume`` (continue them: stored rewards are reused, never
bought again) or ``--overwrite`` (discard them) is given; SIGINT/SIGTERM finish the commit in
flight and end with one line (exit 130/143). The collector's env is the user's, so the example
seeds it itself: every iteration's draws (torch's generator, which the policies and the actor
sample from, and the envs' seeds) come from ``derive_seed(seed, l, stream)``, so a resumed run
buys and measures exactly what an uninterrupted one does.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from _cli import SelectionOptions, ThreadOptions, field, not_here, parse
from _flattening import parse_flattening
from _process import collector_off_for_imports, configure_process, freeze_imported_objects

ENVS = ("CartPole-v1", "MountainCar-v0")  # (_pipeline_envs.ENVS; light here for --help)


@dataclass
class Args(SelectionOptions, ThreadOptions):
    """Command-line arguments of the TorchRL pipeline example."""

    env: str = field("CartPole-v1", choices=ENVS, help="the Gymnasium environment")
    seeds: int = field(5, low=1, help="paired runs: seeds seed, seed+1, …, each AL and PL")
    modes: str = field("AL,PL", choices=("AL,PL", "AL", "PL"), help="which runs of each seed")
    repeats: int = field(2, low=1, help="Z, J-values averaged into J'")
    seed: int = field(
        0,
        low=0,
        help=(
            "first seed: every iteration's draws (torch's generator, the environments' "
            "seeds) are derived from (seed, iteration)"
        ),
    )
    gamma: float = field(
        0.0,
        low=0.0,
        high=1.0,
        help="discount γ in (0, 1]; 0 or auto: the env's default",
    )
    out_dir: str = field("results/torchrl_pipeline", help="where the JSON and the stored run go")
    resume: bool = field(
        False,
        help=(
            "continue the runs stored in out_dir (their stored rewards are reused, never "
            "bought again)"
        ),
    )
    overwrite: bool = field(False, help="discard the runs stored in out_dir and start over")
    iterations: int = field(
        0,
        low=0,
        help="L, policy iterations; 0 or auto: the env's default",
    )
    first_episodes: int = field(
        0,
        low=0,
        help="M_1, rewarded episodes of iteration 1; 0 or auto: the env's default",
    )
    episodes: int = field(
        0,
        low=0,
        help="M, rewarded episodes of each later iteration; 0 or auto: the env's default",
    )
    first_sampler: str = field(
        "pi_1",
        choices=("pi_1", "actor"),
        help="who buys iteration 1's episodes: pi_1 (θ_0 = 1), or the user's actor (warm start)",
    )
    actor_candidate: str = field(
        "auto",
        choices=("auto", "yes", "no"),
        help="the actor among AL's candidates (auto: MountainCar yes, CartPole no)",
    )
    reward_free_episodes: int = field(
        4, low=1, help="reward-free episodes per candidate and repeat (the selector's M)"
    )
    steps: int = field(
        0,
        low=0,
        help="N, longest rewarded episode; 0 or auto: the env's default",
    )
    test_steps: int = field(
        0,
        low=0,
        help="longest greedy test episode; 0 or auto: the env's default",
    )
    test_episodes: int = field(
        0,
        low=0,
        help="greedy test episodes per iteration; 0 or auto: the env's default",
    )
    basis: str = field(
        "auto",
        choices=("auto", "quadratic", "grid"),
        help="basis; 0 or auto: the env's default",
    )
    grid: int = field(5, low=2, help="Gaussian centres per axis of the grid basis")
    tau: float = field(0.4, above=0, help="Gaussian kernel width τ in normalised units")
    fit: str = field(
        "auto",
        choices=("auto", "brm", "lstd"),
        help="the learner; 0 or auto: the env's default",
    )
    flattening: str = field(
        "auto",
        help="ν of the weights w^ν: a number in [0, 1] or iwcv; 0 or auto: the env's default",
    )


UNAVAILABLE = not_here("backend") | {
    "trials": "paired runs over --seeds, one run each, as a user would write it",
    "device": "the envs step in Python on the CPU (Gymnasium); the algebra is small",
}


def check(args: Args) -> str | None:
    try:
        parse_flattening(args.flattening, ("iwcv", "auto"))
    except ValueError as error:
        return str(error)
    return None


def resolved(args: Args) -> Args:
    """``args`` with every 0 / ``auto`` replaced by the environment's default."""
    from _pipeline_envs import DEFAULTS

    fill = {k: v for k, v in DEFAULTS[args.env].items() if getattr(args, k) in (0, "auto")}
    if args.actor_candidate == "auto":
        fill["actor_candidate"] = "yes" if args.env == "MountainCar-v0" else "no"
    return dataclasses.replace(args, **fill)


def parse_args(argv=None) -> Args:
    return parse(Args, argv, __doc__, check=check, unavailable=UNAVAILABLE)


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below
    collector_off_for_imports()  # examples/_process.py: start-up and exit cost less

import json
import logging
import time
from pathlib import Path

import _harness as harness
import _pipeline_envs as envs
import _pipeline_report as report
import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType

from torch_api import LinearQPolicy, PsiHat, SamplingPolicySelector
from torch_api.core.fit import fit_flattened
from torch_api.data.episodes import as_episodes
from torch_api.policies.families import PAPER_EPSILON_OFFSETS
from torch_api.runs.store import RunStore, StoredRun
from torch_api.streams import derive_seed

RESULTS = "torchrl_pipeline.json"


def store_path(out: Path, mode: str, seed: int) -> Path:
    """Where the run (mode, seed) is stored."""
    return out / "checkpoints" / f"{mode}_seed{seed}.db"


def run_config(args: Args, mode: str, seed: int) -> dict:
    """The settings that give a stored run its meaning (a resume must match them)."""
    skip = ("out_dir", "resume", "overwrite", "threads", "seeds", "modes", "seed")
    settings = {k: v for k, v in dataclasses.asdict(args).items() if k not in skip}
    schedule = [args.first_episodes] + [args.episodes] * (args.iterations - 1)
    return settings | {"schedule": schedule, "mode": mode, "seed": seed}


def main(argv=None) -> dict:
    args = resolved(parse_args(argv))
    configure_process(args)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    out = Path(args.out_dir)
    seeds = range(args.seed, args.seed + args.seeds)
    runs = [(mode, seed) for seed in seeds for mode in args.modes.split(",")]
    paths = [store_path(out, mode, seed) for mode, seed in runs]
    outputs = [out / RESULTS, out / "torchrl_pipeline.png"]
    started = time.perf_counter()
    # one run writes the folder; one line on a signal or a store error
    with harness.folder_held(out, paths, outputs, args), harness.durable_runs(paths, out):
        results = {"AL": {}, "PL": {}}
        for (mode, seed), path in zip(runs, paths, strict=True):
            config = run_config(args, mode, seed)
            with RunStore(
                path, config=config, resume=args.resume, overwrite=args.overwrite
            ) as store:
                results[mode][seed] = run(args, mode, seed, store)
    baselines = {seed: envs.actor_alone(args, seed) for seed in seeds}
    payload = report.summarise(args, results, baselines, time.perf_counter() - started)
    (out / RESULTS).write_text(json.dumps(payload, indent=1))
    report.plot(payload, out / "torchrl_pipeline.png")
    print(f"wrote {out / RESULTS} and {out / 'torchrl_pipeline.png'}")
    return payload


def run(args: Args, mode: str, seed_of_run: int, store: RunStore) -> dict:
    """One run of the pipeline, every purchase stored in ``store`` before it is used (what
    ``store`` holds already is used instead of buying it again)."""
    started = time.perf_counter()
    n = args.steps
    stored = store.stored or StoredRun(config=store.config)
    if store.stored is not None:
        print(
            f"resumed {store.path} at iteration {len(stored.records)}/{args.iterations}: "
            f"{stored.num_episodes} rewarded episodes stored"
        )
    elif args.resume:
        print(f"nothing stored in {store.path}: starting it fresh")

    def seed(it: int, stream: str) -> int:
        """The seed of one stream of iteration ``it`` (torch's generator or an env)."""
        return derive_seed(seed_of_run, it, stream)

    env = envs.make_env(args.env, n)
    basis = envs.make_basis(args.env, args.basis, args.grid, args.tau)
    psi = PsiHat(basis=basis, gamma=args.gamma, mode="single")  # continuous states
    nu = parse_flattening(args.flattening)  # (resolved: never auto here)
    selector = None
    if mode == "AL":
        selector = SamplingPolicySelector(
            env=lambda rows: envs.env_rows(args, rows, n),
            psi=psi,
            num_episodes=args.reward_free_episodes,
            num_steps=n,
            num_repeats=args.repeats,
            lam=args.lam,
            fit=args.fit,
        )
    actor = envs.make_actor(args.env, env.action_spec)
    schedule = [args.first_episodes] + [args.episodes] * (args.iterations - 1)
    # The user's own episode stores: one item an episode of N steps (padded, masked).
    capacity = max(sum(schedule), args.iterations * args.repeats * 5 * args.reward_free_episodes)
    rewarded = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity, ndim=1))
    reward_free = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity, ndim=1))

    theta = torch.ones(basis.num_features, dtype=torch.float64)  # Q̂_0 = Σ_b phi_b
    history, bought, nu_j = [], 0, 1.0 if nu == "iwcv" else nu
    for it, m in enumerate(schedule, start=1):
        epsilon = 0.15 / it
        policy = LinearQPolicy(
            basis=basis, theta=theta, epsilon=epsilon, action_spec=env.action_spec
        )
        candidates = {
            f"ε-greedy θ (ε = {epsilon + o:.3f})": policy.with_rule(epsilon=epsilon + o)
            for o in PAPER_EPSILON_OFFSETS
        }
        if args.actor_candidate == "yes":
            candidates[envs.ACTOR_NAME[args.env]] = actor
        # 1. choose the sampling policy from reward-free episodes (Algorithm 2), stored
        if it == 1 and args.first_sampler == "actor":
            selection = {"index": len(candidates), "j_mean": []}  # the user's warm start
            candidates["the actor's warm start"] = actor
        elif selector is None:
            selection = {"index": 0, "j_mean": []}  # passive: pi_l samples
        else:
            if it not in stored.selections:
                torch.manual_seed(seed(it, "reward_free_policy"))  # the candidates' draws
                selector.seed_env(  # the env of the batch the candidates are collected on
                    selector.collection_rows(list(candidates.values())),
                    seed(it, "reward_free_env"),
                )
                earlier = rewarded.storage[: len(rewarded)] if len(rewarded) else None
                choice = selector.select(
                    policy, list(candidates.values()), earlier, iteration=it, flattening=nu_j
                )
                stored.selections[it] = {
                    "index": int(choice.index),
                    "j_mean": choice.j_mean.tolist(),
                    "reward_free_transitions": choice.reward_free_transitions,
                }
                stored.free[it] = as_episodes(
                    choice.episodes.reshape(-1, n), rewarded=False, taken_log_prob=True
                )
                store.put_selection(it, stored.selections[it], stored.free[it])
            selection = stored.selections[it]
            reward_free.extend(stored.free[it])
        name, sampler = list(candidates.items())[selection["index"]]
        # 2. buy M rewarded episodes with it: a Collector yielding whole trajectories, stored
        if len(stored.episodes.get(it, {})) < m:
            torch.manual_seed(seed(it, "policy"))  # the sampler's draws
            collector = Collector(
                envs.env_rows(args, m, n, seed(it, "rewarded_env")),
                sampler,
                frames_per_batch=m * n,
                total_frames=-1,
                trajs_per_batch=m,
                traj_format="padded",
                auto_register_policy_transforms=False,
            )
            batch = next(iter(collector))
            collector.shutdown()
            new = as_episodes(batch, rewarded=True, num_steps=n, taken_log_prob=True)
            stored.episodes[it] = dict(enumerate(new.unbind(0)))
            store.put_episodes(it, stored.episodes[it])
            bought += m
        new = torch.stack([stored.episodes[it][j] for j in range(m)])  # [M, N]
        rewarded.extend(new)
        # 3. fit θ on every rewarded episode so far (eq. 20-28), importance-weighted to pi_l
        episodes = rewarded.storage[: len(rewarded)]
        if it not in stored.records:
            fitted = fit_flattened(args.fit, episodes, policy, psi, basis, args.lam, flattening=nu)
            # 4. the greedy policy of the new θ, tested in env.rollout
            greedy = LinearQPolicy(
                basis=basis, theta=fitted.theta, epsilon=0.0, action_spec=env.action_spec
            )
            torch.manual_seed(seed(it, "evaluation"))
            test_env = envs.env_rows(
                args, args.test_episodes, args.test_steps, seed(it, "evaluation")
            )
            row = {
                "iteration": it,
                "chosen": name,
                "j_mean": selection["j_mean"],
                "rewarded_transitions": int(episodes["mask"].sum()),
                "reward_free_transitions": selection.get("reward_free_transitions", 0),
                "bought_returns": (new["next", "reward"] * new["mask"]).sum(-1).tolist(),
                "flattening": float(fitted.flattening),
                "ess_percent": float(100 * fitted.ess / fitted.num_samples),
                "theta_change": float((fitted.theta - theta).norm()),
                "greedy_test_return": envs.mean_return(
                    greedy, test_env, args.test_steps, ExplorationType.DETERMINISTIC
                ),
            }
            stored.records[it] = row | {"theta": fitted.theta.tolist()}
            store.put_record(it, stored.records[it])
        row = {k: v for k, v in stored.records[it].items() if k != "theta"}
        theta = torch.tensor(stored.records[it]["theta"], dtype=torch.float64)
        nu_j = row["flattening"] if nu == "iwcv" else nu
        history.append(row)
        print(
            f"{mode} seed {seed_of_run} iteration {it}: chose {name!r}, rewarded transitions "
            f"{row['rewarded_transitions']}, ν {row['flattening']:.2f}, ESS "
            f"{row['ess_percent']:.0f} %, |Δθ| {row['theta_change']:.3g}, greedy test return "
            f"{row['greedy_test_return']:.1f}",
            flush=True,
        )
    if selector is not None:
        selector.close()
    wall = time.perf_counter() - started
    print(
        f"{mode} seed {seed_of_run}: bought {bought} rewarded episodes in this run (stored in "
        f"{store.path}); reward-free episodes kept in the user's buffer: {len(reward_free)}; "
        f"{wall:.1f} s wall"
    )
    return {"history": history, "theta": theta.tolist(), "bought": bought, "seconds": wall}


if __name__ == "__main__":
    freeze_imported_objects()
    main()
