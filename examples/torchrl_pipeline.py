"""Active policy iteration inside a plain TorchRL pipeline: CartPole-v1 (or MountainCar-v0).

The user's TorchRL parts, as they are: ``GymEnv`` rows in a ``SerialEnv``, a ``Collector`` buying
rewarded episodes, replay buffers, a ``ProbabilisticActor`` (push the way the pole falls, or the
car moves). The library's ``SamplingPolicySelector`` picks, in each iteration of an active (AL)
run, the candidate whose episodes should fit Q̂ best, by J' of reward-free episodes (a passive (PL)
run samples with pi_l); θ is fitted on all rewarded episodes so far, its greedy policy tested. AL
and PL share their seeds (a paired t-test); runs are stored as they go (``--resume``).

    python examples/torchrl_pipeline.py [--env MountainCar-v0]
"""

import dataclasses
import sys
import time
from functools import partial
from typing import Annotated, Literal

import torch
import tyro
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, GymEnv, ObservationNorm, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType
from torchrl.modules import OneHotCategorical, ProbabilisticActor
from tyro.conf import OmitArgPrefixes

import torch_api.experiment.pipeline as pipe
from torch_api import GaussianActionBasis, LinearQPolicy, PsiHat, RunSpec, SamplingPolicySelector
from torch_api.core.quadratic_basis import QuadraticActionBasis
from torch_api.experiment import Execution
from torch_api.experiment.seeds import run_seeds, seeds_folder, write_seeds
from torch_api.streams import derive_seed


@dataclasses.dataclass
class Args:
    """Command-line arguments of the TorchRL pipeline example (0 or auto: the env's default)."""

    env: Literal["CartPole-v1", "MountainCar-v0"] = "CartPole-v1"
    """the Gymnasium environment (MountainCar: a Gaussian grid basis, the actor a candidate)"""
    seeds: int = 5
    """paired runs: seeds seed, seed+1, …, each AL and PL"""
    seed: int = 0
    """first seed: every draw of a run (torch's generator, the envs' seeds) comes from it"""
    modes: Literal["AL,PL", "AL", "PL"] = "AL,PL"
    """which runs of each seed"""
    iterations: int = 0
    """L, policy iterations"""
    first_episodes: int = 0
    """M_1, rewarded episodes of iteration 1"""
    episodes: int = 0
    """M, rewarded episodes of each later iteration"""
    steps: int = 200
    """N, longest rewarded episode"""
    first_sampler: Literal["pi_1", "actor"] = "pi_1"
    """who buys iteration 1's episodes: pi_1 (θ_0 = 1), or the user's actor (a warm start)"""
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


CARTPOLE = "CartPole-v1"
GOAL = {CARTPOLE: 475.0}  # a last greedy return "learned" (MountainCar: the actor alone's)
RULE = {CARTPOLE: [[0, 0], [0, 0], [-1, 1], [-1, 1]], "MountainCar-v0": [[0, 0, 0], [-1, 0, 1]]}
GRID = torch.cartesian_prod(*[torch.linspace(-1, 1, 5)] * 2)  # 5 × 5 points in [-1, 1]²
BASIS = {  # CartPole: a quadratic Q̂ per action; MountainCar: Gaussians (τ = 0.4) on the grid
    CARTPOLE: lambda: QuadraticActionBasis(obs_dim=4, num_actions=2),
    "MountainCar-v0": lambda: GaussianActionBasis(centers=GRID, tau=0.4, num_actions=3),
}
DEFAULTS = {  # each env's settings where a flag is left at 0 / auto (docs/cartpole_remedies.md)
    CARTPOLE: dict(iterations=8, first_episodes=120, episodes=4, test_steps=500, test_episodes=5,
                   gamma=0.95, fit="lstd", flattening=0.0),
    "MountainCar-v0": dict(iterations=5, first_episodes=6, episodes=6, test_steps=200,
                           test_episodes=10, gamma=0.99, fit="brm", flattening=1.0),
}  # fmt: skip


def resolved(args: Args) -> tuple[Args, RunSpec]:
    """``args`` with each flag left at 0 / auto set to the env's; the run's checked settings."""
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
    if env_id != CARTPOLE:
        box = env.observation_spec["observation"].space
        center, scale = (box.high + box.low) / 2, (box.high - box.low) / 2
    norm = ObservationNorm(loc=center, scale=scale, in_keys=["observation"], standard_normal=True)
    return TransformedEnv(env, Compose(norm, StepCounter(max_steps=max_steps)))


def make_actor(env_id: str) -> ProbabilisticActor:
    """The user's rule, logits 30 · s W (``RULE``): CartPole, push the way the pole falls (angle
    plus angular speed); MountainCar, push the way the car moves (pumping energy into the swing)."""
    w = torch.tensor(RULE[env_id], dtype=torch.float32)
    rule = TensorDictModule(lambda s: 30.0 * (s @ w), ["observation"], ["logits"])
    spec = make_env(env_id, 1).action_spec  # one-hot
    return ProbabilisticActor(rule, in_keys=["logits"], distribution_class=OneHotCategorical,
                              return_log_prob=True, spec=spec)  # fmt: skip


def mean_test_return(args: Args, policy, seed: int, explore=ExplorationType.DETERMINISTIC):
    """The mean return of ``policy`` over ``test_episodes`` seeded test episodes."""
    make = partial(make_env, args.env, args.test_steps)
    return pipe.mean_return(policy, make, args.test_episodes, args.test_steps, seed, explore)


def run(args: Args, spec: RunSpec, mode: str, run_seed: int, store) -> dict:
    """One run: each step is committed to ``store`` before it is used, and never made twice."""
    n, ev, steps = args.steps, spec.evaluation, pipe.StoredSteps(store, run_seed, args.iterations)
    rows = partial(pipe.serial_env, partial(make_env, args.env, n))  # rows(E, seed): E rows
    basis, actor = BASIS[args.env](), make_actor(args.env)
    actions = actor.spec["action"]  # one-hot
    psi = PsiHat(basis=basis, gamma=ev.gamma, mode="single")  # continuous states
    selector = SamplingPolicySelector(env=rows, psi=psi, lam=ev.lam, fit=ev.fit, num_steps=n,
        num_episodes=args.reward_free_episodes, num_repeats=args.repeats)  # fmt: skip
    rewarded = TensorDictReplayBuffer(storage=LazyTensorStorage(sum(spec.rewarded.schedule)))
    free = 5 * args.iterations * args.repeats * args.reward_free_episodes  # K ≤ 5 candidates
    reward_free = TensorDictReplayBuffer(storage=LazyTensorStorage(free))  # the user's buffers
    theta, so_far = torch.ones(basis.num_features, dtype=torch.float64), None  # Q̂_0 = Σ_b phi_b
    nu = 1.0 if ev.flattening == "iwcv" else ev.flattening  # ν of J
    extra = {} if args.env == CARTPOLE else {"push with velocity (ProbabilisticActor)": actor}

    def test(theta_l: torch.Tensor, seed: int) -> dict:  # 4. the greedy policy of θ_l, tested
        greedy = LinearQPolicy(basis=basis, theta=theta_l, epsilon=0.0, action_spec=actions)
        return {"greedy_test_return": mean_test_return(args, greedy, seed)}

    for it, m in enumerate(spec.rewarded.schedule, start=1):
        policy = LinearQPolicy(basis=basis, theta=theta, epsilon=0.15 / it, action_spec=actions)
        candidates = pipe.epsilon_candidates(policy) | extra  # eq. 59, ε_l + offset; the actor
        # 1. the sampling policy: the actor's warm start, pi_l (PL) or J' of the candidates (AL)
        selection = {"index": 0, "j_mean": [], "reward_free_transitions": 0}
        if it == 1 and args.first_sampler == "actor":
            selection["index"], candidates["the actor's warm start"] = len(candidates), actor
        elif mode == "AL":  # (so_far: the rewarded episodes of the iterations before)
            selection, free = steps.choose(it, selector, policy, [*candidates.values()], so_far, nu)
            reward_free.extend(free)
        name, sampler = list(candidates.items())[selection["index"]]
        # 2. M rewarded episodes bought with it: the user's Collector on M fresh rows
        rewarded.extend(new := steps.buy(it, m, rows, sampler, n))
        so_far = rewarded.storage[: len(rewarded)]
        # 3. θ on every rewarded episode so far (eq. 20-28); 4. its greedy policy, tested
        record = steps.fit(it, ev, so_far, policy, psi, basis, theta, test)
        row = steps.row(it, name, new, selection, record)  # the history's row of iteration l
        theta = torch.tensor(record["theta"], dtype=torch.float64)
        nu = record["flattening"] if ev.flattening == "iwcv" else nu
        print(f"{mode} seed {run_seed} l = {it}: {name}; test return {row['greedy_test_return']}")
    selector.close()
    return steps.result(theta, f"{mode} seed {run_seed}")


def main(argv: list[str] | None = None) -> dict:
    try:
        args, spec = resolved(tyro.cli(Args, args=argv, description=__doc__))
        out = seeds_folder(args.execution)
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    started, seeds = time.perf_counter(), range(args.seed, args.seed + args.seeds)
    config = {k: v for k, v in vars(args).items() if k not in ("execution", "seeds", "modes")}
    config["schedule"] = list(spec.rewarded.schedule)  # what a resumed store must match (its seed)
    files = [out / "torchrl_pipeline.json", out / "torchrl_pipeline.png"]
    results = run_seeds(args.execution, args.modes.split(","), seeds, partial(run, args, spec),
                        config=config, files=files)  # fmt: skip
    actor, draw = make_actor(args.env), ExplorationType.RANDOM  # the user's actor alone, sampling
    alone = {s: mean_test_return(args, actor, derive_seed(s, 0, "evaluation"), draw) for s in seeds}
    wall, title = time.perf_counter() - started, f"{args.env} through TorchRL"
    return write_seeds(files[0], dataclasses.asdict(args), results, alone,
                       goal=GOAL.get(args.env), title=title, wall=wall)  # fmt: skip


if __name__ == "__main__":
    main()
