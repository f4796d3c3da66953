"""Active policy iteration inside a plain TorchRL pipeline: CartPole-v1, Acrobot-v1, MountainCar-v0.

The user's ``GymEnv`` rows in a ``SerialEnv``, ``Collector`` and ``ProbabilisticActor`` in one
``ActivePolicyIteration`` a run: AL picks each iteration's sampling policy by J' of reward-free
episodes (MountainCar: the actor a candidate too), PL samples with pi_l; θ is fitted on all the
rewarded episodes so far, its greedy policy tested. AL and PL share their seeds (a paired
t-test); every bought reward is stored as it comes (``--resume`` buys nothing twice).

    python examples/torchrl_pipeline.py [--env Acrobot-v1]
"""

import dataclasses
import sys
import time
from functools import cache, partial
from typing import Annotated, Literal

import torch
import tyro
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs import Compose, GymEnv, ObservationNorm, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType
from torchrl.modules import OneHotCategorical, ProbabilisticActor
from tyro.conf import OmitArgPrefixes

import torch_api.experiment.pipeline as pipe
from torch_api import ActivePolicyIteration, RunSpec, SamplingPolicySelector
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.quadratic_basis import QuadraticActionBasis
from torch_api.experiment import Execution
from torch_api.experiment.seeds import run_seeds, seeds_folder, write_seeds
from torch_api.streams import derive_seed


@dataclasses.dataclass
class Args:
    """Command-line arguments of the TorchRL pipeline example (0 or auto: the env's default)."""

    env: Literal["CartPole-v1", "Acrobot-v1", "MountainCar-v0"] = "CartPole-v1"
    """the Gymnasium environment (MountainCar: a Gaussian grid basis, the actor a candidate)"""
    seeds: int = 5
    """paired runs: seeds seed, seed+1, …, each AL and PL"""
    seed: int = 0
    """first seed: every draw of a run (its streams, the envs' seeds) comes from it"""
    modes: Literal["AL,PL", "AL", "PL"] = "AL,PL"
    """which runs of each seed"""
    iterations: int = 0
    """L, policy iterations"""
    first_episodes: int = 0
    """M_1, rewarded episodes of iteration 1"""
    episodes: int = 0
    """M, rewarded episodes of each later iteration"""
    steps: int = 0
    """N, longest rewarded (and reward-free) episode"""
    repeats: int = 2
    """Z, J-values averaged into J'"""
    reward_free_episodes: int = 4
    """reward-free episodes per candidate and repeat (the selector's M)"""
    gamma: float = 0.0
    """discount γ in (0, 1]"""
    lam: float = 1e-3
    """λ, ridge regularisation"""
    fit: Literal["auto", "brm", "lstd"] = "auto"
    """the learner: BRM (the paper's) or LSTD-Q"""
    flattening: float | Literal["auto", "iwcv"] = "auto"
    """ν of the importance weights w^ν: a number in [0, 1], or iwcv"""
    test_steps: int = 0
    """longest greedy test episode"""
    test_episodes: int = 0
    """greedy test episodes per iteration"""
    execution: Annotated[Execution, OmitArgPrefixes] = Execution("results/torchrl_pipeline")
    """where the JSON, the figure and the stored runs go (--out-dir, --resume, --threads)"""


CARTPOLE, ACROBOT, MOUNTAIN_CAR = "CartPole-v1", "Acrobot-v1", "MountainCar-v0"
GOAL = {CARTPOLE: 475.0, ACROBOT: -100.0}  # a last greedy return "learned" (Gymnasium's)
RULE = {CARTPOLE: [[0, 0], [0, 0], [-1, 1], [-1, 1]], MOUNTAIN_CAR: [[0, 0, 0], [-1, 0, 1]],
        ACROBOT: [[0, 0, 0]] * 4 + [[-1, 0, 1], [0, 0, 0]]}  # fmt: skip
GRID = torch.cartesian_prod(*[torch.linspace(-1, 1, 5)] * 2)  # 5 × 5 points in [-1, 1]²
BASIS = {  # a quadratic Q̂ per action; MountainCar: Gaussians (τ = 0.4) on the grid
    CARTPOLE: lambda: QuadraticActionBasis(obs_dim=4, num_actions=2),
    ACROBOT: lambda: QuadraticActionBasis(obs_dim=6, num_actions=3),
    MOUNTAIN_CAR: lambda: GaussianActionBasis(centers=GRID, tau=0.4, num_actions=3),
}
DEFAULTS = {  # each env's settings where a flag is left at 0 / auto (docs/cartpole_remedies.md)
    CARTPOLE: dict(iterations=8, first_episodes=120, episodes=4, steps=200, test_steps=500,
                   test_episodes=5, gamma=0.95, fit="lstd", flattening=0.0),
    ACROBOT: dict(iterations=6, first_episodes=10, episodes=4, steps=500, test_steps=500,
                  test_episodes=5, gamma=0.99, fit="lstd", flattening=0.0),  # ≤ 15,000 rewarded
    MOUNTAIN_CAR: dict(iterations=5, first_episodes=6, episodes=6, steps=200, test_steps=200,
                       test_episodes=10, gamma=0.99, fit="brm", flattening=1.0),
}  # fmt: skip


def resolved(args: Args) -> tuple[Args, RunSpec]:
    """``args`` with each flag left at 0 / auto set to the env's; the runs' checked settings."""
    unset = {k: v for k, v in DEFAULTS[args.env].items() if getattr(args, k) == getattr(Args, k)}
    args = dataclasses.replace(args, **unset)
    for name in ("seeds", "iterations", "test_steps", "test_episodes"):
        if getattr(args, name) <= 0:
            raise ValueError(f"{name} must be > 0, got {getattr(args, name)}")
    schedule = [args.first_episodes] + [args.episodes] * (args.iterations - 1)
    settings = {k: getattr(args, k) for k in ("gamma", "lam", "fit", "flattening", "seed")}
    spec = RunSpec.of(schedule=schedule, num_steps=args.steps, num_repeats=args.repeats,
                      reward_free_episodes=args.reward_free_episodes, **settings)  # fmt: skip
    return args, spec


def make_env(env_id: str, max_steps: int) -> TransformedEnv:
    """``GymEnv(env_id)`` (one-hot actions), observations to unit scale, ≤ max_steps steps."""
    env = GymEnv(env_id)
    center, scale = torch.zeros(4), torch.tensor([2.4, 2.0, 0.21, 2.0])  # m, m/s, rad, rad/s
    if env_id != CARTPOLE:  # Acrobot: cos, sin in [-1, 1], speeds / 4π, 9π; MountainCar: its box
        box = env.observation_spec["observation"].space
        center, scale = (box.high + box.low) / 2, (box.high - box.low) / 2
    norm = ObservationNorm(loc=center, scale=scale, in_keys=["observation"], standard_normal=True)
    return TransformedEnv(env, Compose(norm, StepCounter(max_steps=max_steps)))


def make_actor(env_id: str) -> ProbabilisticActor:
    """The user's rule, logits 30 · s W (``RULE``): CartPole, push the way the pole falls (angle
    plus angular speed); Acrobot and MountainCar, push the way the first link (the car) moves."""
    w = torch.tensor(RULE[env_id], dtype=torch.float32)
    rule = TensorDictModule(lambda s: 30.0 * (s @ w), ["observation"], ["logits"])
    spec = make_env(env_id, 1).action_spec  # one-hot
    return ProbabilisticActor(rule, in_keys=["logits"], distribution_class=OneHotCategorical,
                              return_log_prob=True, spec=spec)  # fmt: skip


def mean_test_return(args: Args, policy, seed: int, explore=ExplorationType.DETERMINISTIC):
    """The mean return of ``policy`` over ``test_episodes`` seeded test episodes."""
    make = partial(make_env, args.env, args.test_steps)
    return pipe.mean_return(policy, make, args.test_episodes, args.test_steps, seed, explore)


def history_row(record) -> dict:
    """An iteration's row of the run's history: the loop's record's, the sampler named."""
    rule = record.sampling_rule
    name = "the actor (ProbabilisticActor)" if rule is None else f"ε-greedy θ (ε = {rule:.3f})"
    row = record.row() | {"j_mean": record.j_mean or [], "chosen": name}
    return {k: v for k, v in row.items() if k not in ("seconds", "selection_cpu_seconds")}


def run(args: Args, spec: RunSpec, mode: str, run_seed: int, durable) -> dict:
    """One run, each bought reward committed to ``durable`` (a DurableRun) before it is used."""
    n, started, bought = args.steps, time.perf_counter(), []
    rows = cache(partial(pipe.serial_env, partial(make_env, args.env, n)))  # rows(E): E envs
    basis, actor = BASIS[args.env](), make_actor(args.env)
    spec = spec.replace(seed=run_seed, mode="active" if mode == "AL" else "passive")
    extra = [actor] if args.env == MOUNTAIN_CAR and mode == "AL" else []  # the user's candidate

    def collector(policy, m: int) -> Collector:  # 2. M rewarded episodes (the loop seeds M rows)
        bought.append(m)
        torch.manual_seed(derive_seed(run_seed, api.iteration + 1, "policy"))  # (the actor's)
        return Collector(rows(m), policy, frames_per_batch=m * n, total_frames=-1,
                         trajs_per_batch=m, traj_format="padded",
                         auto_register_policy_transforms=False)  # fmt: skip

    def test(policy, seed: int) -> dict:  # 4. the greedy policy of θ_l, tested
        test_return = mean_test_return(args, policy.with_rule(epsilon=0.0), seed)  # greedy
        print(f"{mode} seed {run_seed} l = {api.iteration + 1}: greedy test return {test_return}")
        return {"greedy_test_return": test_return}

    def next_choice(record=None) -> None:  # torch seeded for the actor's reward-free draws
        torch.manual_seed(derive_seed(run_seed, api.iteration + 1, "reward_free_policy"))

    selector = SamplingPolicySelector(env=rows) if mode == "AL" else None  # Z·K·R rows
    with ActivePolicyIteration(spec, env=rows, basis=basis, selector=selector, durable=durable,
                               evaluate=test, collector=collector, extra_candidates=extra,
                               on_iteration=next_choice) as api:  # fmt: skip
        if api.resumed:
            print(f"resumed {durable.path} at iteration {api.iteration}/{len(api.schedule)}")
        next_choice()
        api.run()
    history, seconds = [history_row(r) for r in api.history], time.perf_counter() - started
    return {"history": history, "theta": api.theta.tolist(), "bought": sum(bought),
            "seconds": seconds}  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    try:
        args, spec = resolved(tyro.cli(Args, args=argv, description=__doc__))
        out = seeds_folder(args.execution)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    started, seeds = time.perf_counter(), range(args.seed, args.seed + args.seeds)
    files = [out / "torchrl_pipeline.json", out / "torchrl_pipeline.png"]
    test = {"test_steps": args.test_steps, "test_episodes": args.test_episodes}  # resume: same
    results = run_seeds(args.execution, args.modes.split(","), seeds, partial(run, args, spec),
                        files=files, settings=test)  # fmt: skip
    actor, draw = make_actor(args.env), ExplorationType.RANDOM  # the user's actor alone, sampling
    alone = {s: mean_test_return(args, actor, derive_seed(s, 0, "evaluation"), draw) for s in seeds}
    wall, title = time.perf_counter() - started, f"{args.env} through TorchRL"
    return write_seeds(files[0], dataclasses.asdict(args), results, alone,
                       goal=GOAL.get(args.env), title=title, wall=wall)  # fmt: skip


if __name__ == "__main__":
    main()
