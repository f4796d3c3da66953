"""Active policy iteration inside a plain TorchRL pipeline, on MountainCar-v0 as GymEnv gives it.

What a TorchRL user already has, used as it is: ``GymEnv("MountainCar-v0")`` with its one-hot
actions, an ``ObservationNorm`` (the observation box mapped to [-1, 1]) and a ``StepCounter``
(episodes of at most N steps), batched by ``SerialEnv``; a ``Collector`` that buys the rewarded
episodes; two ``TensorDictReplayBuffer``s of the user's own, one for reward-free and one for
rewarded episodes; and the user's own candidate sampling policies, one of them a
``ProbabilisticActor`` (a hand-made "push the way the car moves" rule).

What the library adds: :class:`~torch_api.loop.selector.SamplingPolicySelector` chooses, every
iteration, the candidate whose rewarded episodes should give the most accurate value function,
from reward-free episodes alone (the paper's J criterion, Algorithm 2); the functional pieces
(``build_design``: psi_hat and the per-decision importance weights; ``weighted_ridge``) fit θ
on every rewarded episode so far (sample reuse); the new ε-greedy policy of θ then drives the
next iteration. At the end the greedy policy of θ runs in ``env.rollout`` under
``ExplorationType.DETERMINISTIC``.

MountainCar pays -1 per step until the car reaches the flag (at most 200 steps): the return of a
test episode is minus its length, -200 when the car never gets there.

    python examples/torchrl_pipeline.py

Durable, like every experiment example: the user's pipeline keeps what it buys in the library's
:class:`~torch_api.runs.store.RunStore` at ``<out-dir>/checkpoints/torchrl_pipeline.db`` — each
iteration's selection (J', the reward-free episodes) before the rewarded episodes it buys, those
episodes before θ is fitted on them, θ and the iteration's row after. A folder holding a run is
refused unless ``--resume`` (continue it: stored rewards are reused, never bought again) or
``--overwrite`` (discard it) is given; SIGINT/SIGTERM finish the commit in flight and end with
one line (exit 130/143). The collector's env is the user's, so the example seeds it itself: every
iteration's draws (torch's generator, which the policies and the actor sample from, and the
envs' seeds) come from ``derive_seed(seed, l, stream)``, not from one stream running through the
whole run, so a resumed run buys and measures exactly what an uninterrupted one does.
"""

from __future__ import annotations

from dataclasses import dataclass

from _cli import SelectionOptions, ThreadOptions, field, not_here, parse, use_threads


@dataclass
class Args(SelectionOptions, ThreadOptions):
    """Command-line arguments of the TorchRL pipeline example."""

    repeats: int = field(2, low=1, help="Z, J-values averaged into J'")
    seed: int = field(
        0,
        low=0,
        help=(
            "seed of the run: every iteration's draws (torch's generator, the environments' "
            "seeds) are derived from (seed, iteration)"
        ),
    )
    gamma: float = field(0.99, above=0.0, high=1.0, help="discount γ, in (0, 1]")
    out_dir: str = field("results/torchrl_pipeline", help="where the JSON and the stored run go")
    resume: bool = field(
        False,
        help=(
            "continue the run stored in out_dir (its stored rewards are reused, never bought again)"
        ),
    )
    overwrite: bool = field(False, help="discard the run stored in out_dir and start over")
    iterations: int = field(5, low=1, help="L, policy iterations")
    episodes: int = field(
        6, low=1, help="M, rewarded episodes bought per iteration (by the Collector)"
    )
    reward_free_episodes: int = field(
        4, low=1, help="reward-free episodes per candidate and repeat (the selector's M)"
    )
    steps: int = field(
        200,
        low=1,
        help="N, longest episode (StepCounter's max_steps; MountainCar's own limit is 200)",
    )
    grid: int = field(
        5,
        low=2,
        help=(
            "Gaussian centres on a grid × grid lattice over the normalised (position, velocity) box"
        ),
    )
    tau: float = field(0.4, above=0, help="Gaussian kernel width τ in normalised units")
    test_episodes: int = field(
        10, low=1, help="greedy test episodes of the policy after every iteration"
    )


UNAVAILABLE = not_here("backend") | {
    "trials": "one run of the pipeline, as a user would write it",
    "device": "MountainCar steps in Python on the CPU (Gymnasium); the algebra is small",
}


def parse_args(argv=None) -> Args:
    return parse(Args, argv, __doc__, unavailable=UNAVAILABLE)


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below

import dataclasses
import json
import logging
import time
from functools import partial
from pathlib import Path

import _harness as harness
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, GymEnv, ObservationNorm, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import OneHotCategorical, ProbabilisticActor

from torch_api import GaussianActionBasis, LinearQPolicy, PsiHat, SamplingPolicySelector
from torch_api.core.design import build_design
from torch_api.core.solve import weighted_ridge
from torch_api.data.episodes import as_episodes
from torch_api.runs.store import RunStore, StoredRun
from torch_api.streams import derive_seed

ENV_ID = "MountainCar-v0"
STORE = "checkpoints/torchrl_pipeline.db"
"""the run's store, under --out-dir"""


def make_env(max_steps: int) -> TransformedEnv:
    """One MountainCar as GymEnv gives it (one-hot actions), observations mapped to [-1, 1]."""
    env = GymEnv(ENV_ID)
    box = env.observation_spec["observation"].space
    center, half_width = (box.high + box.low) / 2, (box.high - box.low) / 2
    norm = ObservationNorm(
        loc=center, scale=half_width, in_keys=["observation"], standard_normal=True
    )
    return TransformedEnv(env, Compose(norm, StepCounter(max_steps=max_steps)))


class PushWithVelocity(nn.Module):
    """Logits of a hand-made rule: push the way the car moves (it pumps energy into the swing)."""

    def __init__(self, sharpness: float = 30.0) -> None:
        super().__init__()
        self.sharpness = sharpness

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        velocity = observation[..., 1:2]  # normalised, in [-1, 1]
        return self.sharpness * torch.cat([-velocity, torch.zeros_like(velocity), velocity], -1)


def mean_return(policy, env, steps: int, exploration: ExplorationType) -> float:
    """Mean return of one ``env.rollout`` of ``policy`` (one episode a row of ``env``)."""
    with set_exploration_type(exploration):
        rollout = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    done = as_episodes(rollout, rewarded=True)  # steps after each episode's end are masked
    return float((done["next", "reward"] * done["mask"]).sum(-1).mean())


def run_config(args: Args) -> dict:
    """The settings that give the stored run its meaning (a resume must match them)."""
    skip = ("out_dir", "resume", "overwrite", "threads")  # threads change no number
    settings = {k: v for k, v in dataclasses.asdict(args).items() if k not in skip}
    return settings | {"schedule": [args.episodes] * args.iterations}


def main(argv=None) -> dict:
    args = parse_args(argv)
    use_threads(args)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    out = Path(args.out_dir)
    path, outputs = out / STORE, [out / "torchrl_pipeline.json"]
    # one run writes the folder; one line on a signal or a store error
    with harness.folder_held(out, [path], outputs, args), harness.durable_runs([path], path.parent):
        config = run_config(args)
        with RunStore(path, config=config, resume=args.resume, overwrite=args.overwrite) as store:
            return run(args, store)


def run(args: Args, store: RunStore) -> dict:
    """The pipeline, every purchase stored in ``store`` before it is used (what ``store``
    holds already is used instead of buying it again)."""
    started = time.perf_counter()
    n, m = args.steps, args.episodes
    stored = store.stored or StoredRun(config=store.config)
    if store.stored is not None:
        print(
            f"resumed {store.path} at iteration {len(stored.records)}/{args.iterations}: "
            f"{stored.num_episodes} rewarded episodes stored"
        )
    elif args.resume:
        print(f"nothing stored in {store.path}: starting it fresh")

    def env_rows(rows: int, seed: int | None = None) -> SerialEnv:
        env = SerialEnv(rows, partial(make_env, n))
        if seed is not None:
            env.set_seed(seed)
        return env

    def seed(it: int, stream: str) -> int:
        """The seed of one stream of iteration ``it`` (torch's generator or an env)."""
        return derive_seed(args.seed, it, stream)

    env = make_env(n)
    axis = torch.linspace(-1, 1, args.grid)
    centers = torch.cartesian_prod(axis, axis)  # [grid², 2] in normalised units
    basis = GaussianActionBasis(centers=centers, tau=args.tau, num_actions=3)
    psi = PsiHat(basis=basis, gamma=args.gamma, mode="single")  # continuous states
    selector = SamplingPolicySelector(
        env=env_rows,
        psi=psi,
        num_episodes=args.reward_free_episodes,
        num_steps=n,
        num_repeats=args.repeats,
        lam=args.lam,
    )
    actor = ProbabilisticActor(
        TensorDictModule(PushWithVelocity(), in_keys=["observation"], out_keys=["logits"]),
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
        return_log_prob=True,  # the sampling probability the importance weights need
        spec=env.action_spec,
    )
    # The user's own episode stores: one item an episode of N steps (padded, masked).
    capacity = args.iterations * max(m, args.repeats * 3 * args.reward_free_episodes)
    rewarded = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity, ndim=1))
    reward_free = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity, ndim=1))

    theta = torch.ones(basis.num_features, dtype=torch.float64)  # Q̂_0 = Σ_b phi_b
    history, bought = [], 0
    for it in range(1, args.iterations + 1):
        epsilon = 0.15 / it
        policy = LinearQPolicy(
            basis=basis, theta=theta, epsilon=epsilon, action_spec=env.action_spec
        )
        candidates = {
            f"ε-greedy θ (ε = {epsilon:.3f})": policy,
            f"ε-greedy θ (ε = {epsilon + 0.5:.3f})": policy.with_rule(epsilon=epsilon + 0.5),
            "push with velocity (ProbabilisticActor)": actor,
        }
        # 1. choose the sampling policy from reward-free episodes (Algorithm 2), stored
        if it not in stored.selections:
            torch.manual_seed(seed(it, "reward_free_policy"))  # the candidates' draws
            selector.seed_env(args.repeats * args.reward_free_episodes, seed(it, "reward_free_env"))
            earlier = rewarded.storage[: len(rewarded)] if len(rewarded) else None
            choice = selector.select(policy, list(candidates.values()), earlier, iteration=it)
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
                env_rows(m, seed(it, "rewarded_env")),
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
            design = build_design(episodes, policy, psi)
            theta = weighted_ridge(
                design.x, design.w, design.reward, args.lam, num_samples=design.num_samples
            )
            # 4. the greedy policy of the new θ, tested in env.rollout
            greedy = LinearQPolicy(
                basis=basis, theta=theta, epsilon=0.0, action_spec=env.action_spec
            )
            torch.manual_seed(seed(it, "evaluation"))
            test_env = env_rows(args.test_episodes, seed(it, "evaluation"))
            row = {
                "iteration": it,
                "chosen": name,
                "j_mean": selection["j_mean"],
                "rewarded_transitions": int(episodes["mask"].sum()),
                "reward_free_transitions": selection["reward_free_transitions"],
                "bought_returns": (new["next", "reward"] * new["mask"]).sum(-1).tolist(),
                "greedy_test_return": mean_return(
                    greedy, test_env, n, ExplorationType.DETERMINISTIC
                ),
            }
            stored.records[it] = row | {"theta": theta.tolist()}
            store.put_record(it, stored.records[it])
        row = {k: v for k, v in stored.records[it].items() if k != "theta"}
        theta = torch.tensor(stored.records[it]["theta"], dtype=torch.float64)
        history.append(row)
        print(
            f"iteration {it}: chose {name!r} (J' = "
            + ", ".join(f"{j:.3g}" for j in row["j_mean"])
            + f"), rewarded transitions {row['rewarded_transitions']}, greedy test return "
            f"{row['greedy_test_return']:.1f}",
            flush=True,
        )
    selector.close()
    torch.manual_seed(seed(0, "evaluation"))  # the actor alone, sampling
    test_env = env_rows(args.test_episodes, seed(0, "evaluation"))
    baseline = {
        "push with velocity (ProbabilisticActor, RANDOM)": mean_return(
            actor, test_env, n, ExplorationType.RANDOM
        ),
    }
    wall = time.perf_counter() - started
    print(f"the actor candidate alone (sampling): mean return {list(baseline.values())[0]:.1f}")
    print(f"reward-free episodes kept in the user's buffer: {len(reward_free)}; {wall:.1f} s wall")
    print(f"bought {bought} rewarded episodes in this run (stored in {store.path})")
    out = Path(args.out_dir)
    payload = {
        "args": dataclasses.asdict(args),
        "wall_seconds": wall,
        "history": history,
        "baseline": baseline,
        "theta": theta.tolist(),
    }
    (out / "torchrl_pipeline.json").write_text(json.dumps(payload, indent=1))
    print(f"wrote {out}/torchrl_pipeline.json")
    return payload


if __name__ == "__main__":
    main()
