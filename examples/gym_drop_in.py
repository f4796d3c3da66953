"""Active vs passive policy iteration on Gymnasium's CartPole-v1 through TorchRL (a drop-in demo).

The library's selector and iteration loop are not tied to this project's environments: any
TorchRL env with discrete actions works. Here the env is Gymnasium's ``CartPole-v1`` wrapped by
``torchrl.envs.GymWrapper`` (the base class of ``GymEnv``) around a
``gymnasium.vector.SyncVectorEnv`` of E copies with ``autoreset_mode=DISABLED``: one process,
batch size ``[E]``, and TorchRL resets finished rows itself (``"_reset"``), so the terminal step
keeps its true next observation. (``GymEnv("CartPole-v1", num_envs=E)`` in torchrl 0.14.1 builds
an ``AsyncVectorEnv`` with E worker processes — about 11 s to start 4 of them here, and the
reward-free batches need thousands — and under its NEXT_STEP auto-reset the terminal step's next
observation comes back as zeros; gymnasium's own ``CartPoleVectorEnv`` is NEXT_STEP only, which
GymWrapper refuses.)

Observations are normalised by a TorchRL ``ObservationNorm`` transform,
``s ↦ s / (2.4, 2.0, 0.21, 2.0)`` (cart position, cart velocity, pole angle, pole angular
velocity: the position and angle limits of the task map to ±1, velocities to roughly ±1). The
basis is :class:`~torch_api.core.basis.GaussianActionBasis` with centres on the grid
``{-g, g}^4`` ∪ {0} in normalised units and ``psi_mode="single"`` (continuous states).

CartPole pays +1 per step and terminates when the pole falls; an episode of N steps may end
early. The library masks the steps after an episode's end and drops the bootstrap term of
psi_hat where ``("next", "terminated")`` is set; :func:`check_episodes` verifies on the bought
data that every episode's mask stops exactly at its first terminal step and that terminal next
states lie outside the task's limits (the true next observation, not a reset one).

Performance of pi_{l+1} after every iteration: the mean number of steps the pole stays up over
test episodes of at most ``test_steps`` steps, with the policy's own ε-greedy rule and with its
greedy version (ε = 0).

    python examples/gym_drop_in.py

A Gymnasium env steps its rows one by one in Python, so this is where reward-free collection in
worker processes (TorchRL's ``MultiSyncCollector``) can pay: each worker steps its share of the
CartPoles. The policies' per-trial streams travel with the trials, but each worker's CartPoles
are seeded on their own, so the numbers are an equally valid sample, not those of one process.

    python examples/gym_drop_in.py --reward-free-workers 2

Outputs in ``--out-dir`` (``examples/_harness.py``): ``gym_drop_in.csv`` (every number, one
row per method × iteration × trial × measure; the schedule column reads ``custom``),
``gym_drop_in.json`` (arguments, the t-test, the checks of the bought data) and
``performance.png``.

Durable runs: AL and PL are stored as they go in ``<out-dir>/checkpoints/{active,passive}.db``
(``torch_api/runs/store.py``): the rewarded episodes of an iteration are committed before the next
are measured. A folder holding runs is refused unless ``--resume`` (continue them, buying only
what is missing) or ``--overwrite`` (discard them) is given; SIGINT/SIGTERM finish the commit in
flight and end with one line (exit 130/143).
"""

from __future__ import annotations

from dataclasses import dataclass

from _cli import RunOptions, SelectionOptions, field, parse
from _process import collector_off_for_imports, freeze_imported_objects


@dataclass
class Args(SelectionOptions, RunOptions):
    """Command-line arguments of the CartPole drop-in demo."""

    trials: int = field(
        8, low=2, why="(a paired t-test needs two)", help="independent trials, all run as one batch"
    )
    out_dir: str = field(
        "results/gym_drop_in", help="where the JSON, the CSV, the figure and the stored runs go"
    )
    schedule: str = field(
        "10,10,6,6,6,2,2", help="rewarded episodes per iteration, comma-separated (its length is L)"
    )
    iterations: int = field(
        0, low=0, help="run only the first L iterations of the schedule (0: all)"
    )
    steps: int = field(
        25, low=1, help="N, steps per episode (an episode may end earlier when the pole falls)"
    )
    gamma: float = field(0.95, above=0.0, high=1.0, help="discount γ, in (0, 1]")
    grid: float = field(
        0.5,
        above=0,
        help="Gaussian centres at ±grid in every normalised coordinate (2^4 = 16) plus the origin",
    )
    tau: float = field(0.75, above=0, help="Gaussian kernel width τ in normalised units")
    test_episodes: int = field(20, low=1, help="test episodes per trial and iteration")
    test_steps: int = field(200, low=1, help="longest test episode (steps)")
    reward_free_workers: int = field(
        0,
        low=0,
        help=(
            "if > 0, collect the reward-free episodes in this many worker processes (TorchRL's "
            "MultiSyncCollector; each steps its share of the CartPoles)"
        ),
    )


UNAVAILABLE = {
    "device": "CartPole steps in Python on the CPU (Gymnasium); the algebra is small",
    "backend": "all trials run as one batch here (--reward-free-workers spreads the reward-free "
    "collection over processes)",
}


def schedule_of(args: Args) -> tuple[int, ...]:
    """M_l of the iterations run: ``--schedule``, cut to ``--iterations`` if given."""
    schedule = tuple(int(m) for m in args.schedule.split(","))
    return schedule[: args.iterations] if args.iterations else schedule


def check(args: Args) -> str | None:
    try:
        schedule = tuple(int(m) for m in args.schedule.split(","))
    except ValueError:
        schedule = ()
    if not schedule or min(schedule) < 1:
        return f"--schedule must be episode counts >= 1 separated by commas, got {args.schedule!r}"
    if args.iterations > len(schedule):
        return f"--iterations must lie in 0..{len(schedule)} (the schedule), got {args.iterations}"
    return None


def parse_args(argv=None) -> Args:
    return parse(Args, argv, __doc__, check=check, unavailable=UNAVAILABLE)


if __name__ == "__main__":
    parse_args()  # --help and bad flags answer here, before the heavy imports below
    collector_off_for_imports()  # examples/_process.py: start-up and exit cost less

import itertools
import math
from pathlib import Path

import _harness as harness
import gymnasium as gym
import numpy as np
import torch
from _figures import steps_balanced
from torchrl.envs import GymWrapper, ObservationNorm, TransformedEnv

from counter_rng import CounterStreams, derive_keys
from torch_api.collection import collect_episodes
from torch_api.core.basis import GaussianActionBasis
from torch_api.data import REWARD_KEY
from torch_api.policies import LinearQPolicy

ENV_ID = "CartPole-v1"
OBS_SCALE = (2.4, 2.0, 0.21, 2.0)  # (m, m/s, rad, rad/s): normalised observation = s / scale
X_LIMIT, ANGLE_LIMIT = 2.4, 12 * 2 * math.pi / 360  # CartPole's termination limits (m, rad)
MEASURES = ("steps_balanced", "steps_balanced_greedy")
_ROLE_TEST, _ROLE_TEST_GREEDY = 1, 2  # the test policies' streams, derived from pi_{l+1}'s


def make_env(batch: int) -> TransformedEnv:
    """E = ``batch`` CartPoles as one TorchRL env ``[E]`` with normalised observations."""
    vector = gym.vector.SyncVectorEnv(
        [lambda: gym.make(ENV_ID)] * batch, autoreset_mode=gym.vector.AutoresetMode.DISABLED
    )
    env = GymWrapper(vector, categorical_action_encoding=True)
    norm = ObservationNorm(  # standard_normal: (s - loc) / scale (else s * scale + loc)
        loc=torch.zeros(4),
        scale=torch.tensor(OBS_SCALE),
        in_keys=["observation"],
        standard_normal=True,
    )
    return TransformedEnv(env, norm)


def make_basis(args: Args) -> GaussianActionBasis:
    corners = torch.tensor(list(itertools.product((-args.grid, args.grid), repeat=4)))
    centers = torch.cat([corners, torch.zeros(1, 4)])  # [17, 4]
    return GaussianActionBasis(centers=centers, tau=args.tau, num_actions=2)


def check_episodes(episodes) -> dict:
    """Check bought CartPole episodes ``[T, M, N]`` and summarise them.

    Raises:
        ValueError: a mask that does not stop at an episode's first terminal step, or a terminal
            next state inside the task's limits (a reset observation in its place).
    """
    mask, terminated = episodes["mask"], episodes["next", "terminated"]
    steps = mask.shape[-1]
    first_end = torch.where(terminated.any(-1), terminated.long().argmax(-1), steps - 1)
    expected = torch.arange(steps) <= first_end.unsqueeze(-1)
    if not torch.equal(mask, expected):
        raise ValueError("the mask does not end at the first terminal step of every episode")
    final = episodes["next", "observation"][terminated & mask]  # normalised units
    raw = final * torch.tensor(OBS_SCALE)
    outside = (raw[:, 0].abs() > X_LIMIT) | (raw[:, 2].abs() > ANGLE_LIMIT)
    if not outside.all():
        raise ValueError(
            f"{int((~outside).sum())} terminal next states lie inside CartPole's limits"
        )
    ended = terminated.any(-1)
    return {
        "episodes": int(math.prod(mask.shape[:-1])),
        "transitions": int(mask.sum()),
        "share_ended_early": float(ended.double().mean()),
        "mean_length": float(mask.sum(-1).double().mean()),
        "rewards_in_masked_steps": float(episodes[REWARD_KEY][mask].sum()),
    }


def make_evaluator(args: Args):
    """The ``evaluate`` callback: mean steps balanced by pi_{l+1} (ε-greedy and greedy).

    The policy comes with one sampling stream per trial (from ``api.block_seeds(l,
    "evaluation")``); the test policies draw from streams derived from those, and the test
    env's CartPole row ``r`` is seeded ``seed + r`` (Gymnasium's vector seeding), so trial t's
    test episodes do not depend on how many trials run beside it.
    """
    trials, m, n = args.trials, args.test_episodes, args.test_steps
    env = make_env(trials * m)

    def balanced(policy: LinearQPolicy, epsilon, role: int) -> torch.Tensor:
        tester = LinearQPolicy(
            basis=policy.basis,
            theta=policy.theta,
            epsilon=epsilon,
            tie_break=policy.tie_break,
            streams=CounterStreams(derive_keys(policy.counter_streams.keys, role)),
        )
        episodes = collect_episodes(env, tester, num_episodes=m, num_steps=n, rewarded=True)
        return (episodes[REWARD_KEY] * episodes["mask"]).sum(-1).double().mean(-1)  # [T]

    def evaluate(policy: LinearQPolicy, seed: int | None = None) -> dict:
        if seed is not None:  # the same test noise for AL and PL at iteration l
            env.set_seed(int(seed))
        return {
            "steps_balanced": balanced(policy, policy.epsilon, _ROLE_TEST).tolist(),
            "steps_balanced_greedy": balanced(policy, 0.0, _ROLE_TEST_GREEDY).tolist(),
        }

    return evaluate


def run_chunk(chunk: harness.Chunk) -> dict:
    """One batched run of Algorithm 1 (all trials), stored as it goes; its bought data checked."""
    args = chunk.args
    evaluate = make_evaluator(args)
    api = harness.make_iteration(
        chunk,
        repeats=args.repeats,
        env=make_env,
        reward_free_env=make_env if args.reward_free_workers else None,
        reward_free_workers=args.reward_free_workers,
        basis=make_basis(args),
        schedule=chunk.schedule,
        num_steps=args.steps,
        gamma=args.gamma,
        lam=args.lam,
        psi_mode="single",
        evaluate=evaluate,
        keep_reward_free=False,
    )
    first = api.initial_policy().with_streams(CounterStreams(api.block_seeds(0, "evaluation")))
    initial = evaluate(first, args.seed + 1)  # pi_1: iteration 0
    run = harness.run_iterations(chunk, api, initial=initial)
    return run | {"data_check": check_episodes(api.rewarded.episodes())}


def report(args: Args, experiment: harness.Experiment, results: dict, wall: float) -> dict:
    """The tables, the files (JSON, CSV, figure) of a finished experiment."""
    print(f"\n{ENV_ID}: {args.trials} trials, mean ± s.e. over trials ({wall:.1f} s)")
    title = f"steps balanced (of {args.test_steps}) by pi_(l+1), its ε-greedy rule"
    harness.print_curves(results, "steps_balanced", title, digits=1)
    harness.print_curves(results, "steps_balanced_greedy", "the same, greedy", digits=1)
    for method, run in results["custom"]["runs"].items():
        chosen = [np.bincount(it["chosen"], minlength=4).tolist() for it in run["iterations"][1:]]
        print(f"{method}: candidates chosen per iteration (counts of k = 1..4): {chosen}")
        print(f"{method}: bought data {run['data_check']}")
    harness.print_t_tests(results, args.trials)
    payload = harness.write_results(args, experiment, results, wall)
    steps_balanced(results, ENV_ID, Path(args.out_dir) / "performance.png")
    print(f"wrote {args.out_dir}/gym_drop_in.json, gym_drop_in.csv and performance.png")
    return payload


def main(argv=None) -> dict:
    args = parse_args(argv)
    experiment = harness.Experiment(
        name="gym_drop_in",
        schedules={"custom": schedule_of(args)},
        run_chunk=run_chunk,
        t_tests=("steps_balanced",),
        report=lambda results, wall: report(args, experiment, results, wall),
        store_stem="{mode}",
        curves=MEASURES,
        files=("performance.png",),
    )
    return harness.run_experiment(args, experiment)


if __name__ == "__main__":
    freeze_imported_objects()
    main()
