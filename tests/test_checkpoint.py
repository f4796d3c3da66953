"""Durable runs: resume equals the uninterrupted run, nothing is bought twice or overwritten
silently, and bad files, bad places and other settings are refused with the path named."""

import _thread
import math
import os
import pickle
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

import torch_api.core.solve
from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.core.criterion import j_eq46
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.runs.store import (
    CorruptRunError,
    RunExistsError,
    RunInUseError,
    RunStore,
    StoreWriteError,
)

ROOT = Path(__file__).resolve().parents[1]


def _half_j(moments, lam):
    """A criterion other than the default (its choices are J's: it is J halved)."""
    return j_eq46(moments, lam) / 2


def _api(
    path=None,
    trials=3,
    mode="active",
    env=ChainWalkEnv,
    repeats=2,
    criterion=j_eq46,
    centers=None,
    tau=TAU,
    resume=False,
    overwrite=False,
    on_commit=None,
    device=None,
    **settings,
):
    """A chain-walk run of 3 trials (stored at ``path``); ``settings`` are the spec's fields."""
    centers = torch.tensor(CENTERS)[:, None] if centers is None else centers
    basis = GaussianActionBasis(centers=centers, tau=tau, num_actions=2)
    settings = {"schedule": (3, 2, 2), "gamma": GAMMA, "num_steps": 10, "seed": 7} | settings
    spec = RunSpec.of(
        psi_mode="grouped",
        num_trials=trials,
        mode=mode,
        **({"num_repeats": repeats} if mode == "active" else {}),
        **settings,
    )
    durable = None
    if path is not None:
        durable = DurableRun(path, resume=resume, overwrite=overwrite, on_commit=on_commit)
    return ActivePolicyIteration(
        spec,
        env=lambda e: env(batch_size=e),
        basis=basis,
        selector=SamplingPolicySelector(criterion=criterion) if mode == "active" else None,
        durable=durable,
        device=device,
    )


def _same_run(a, b):
    """Same θ, choices, J' and the very same bought episodes, tensor by tensor."""
    assert torch.equal(a.theta, b.theta)
    counts = ("chosen", "j_mean", "rewarded_transitions", "reward_free_transitions")
    assert [[getattr(r, c) for c in counts] for r in a.history] == [
        [getattr(r, c) for c in counts] for r in b.history
    ]
    ea, eb = a.rewarded.episodes(), b.rewarded.episodes()
    assert set(ea.keys(True, True)) == set(eb.keys(True, True))
    for key in ea.keys(True, True):
        assert torch.equal(ea[key], eb[key]), key


@pytest.fixture(scope="module")
def full():
    api = _api()
    api.run()
    return api


class _CountingChain(ChainWalkEnv):
    """Counts the rewarded steps measured (the rewarded env has T·M_l rows, M_l <= 3)."""

    measured = 0

    def _step(self, td):
        if self.batch_size[0] <= 9:
            type(self).measured += self.batch_size[0]
        return super()._step(td)


def test_resume_after_rewards_bought_but_not_fitted_buys_nothing_again(tmp_path, full):
    path = tmp_path / "run.db"
    first = _api(path, env=_CountingChain)
    first.step()
    first.buy()  # rewards of iteration 2 bought and committed, θ_2 not yet fitted
    first.close()
    bought = _CountingChain.measured
    assert bought == 3 * (3 + 2) * 10
    resumed = _api(path, env=_CountingChain, resume=True)
    assert resumed.resumed and resumed.iteration == 1 and len(resumed.rewarded) == 3 + 2
    resumed.run()
    assert _CountingChain.measured - bought == 3 * 2 * 10  # only iteration 3's rewards
    _same_run(full, resumed)


def test_going_on_after_a_stop_at_the_selections_commit_buys_as_a_resume(tmp_path, full):
    """A hook that raises at iteration 2's selection commit (the run's 4th): the same object
    going on buys what a resumed run buys, the uninterrupted run's episodes."""

    def stop_at_the_fourth(counter):
        def hook():
            counter.append(1)
            if len(counter) == 4:
                raise KeyboardInterrupt

        return hook

    going_on = _api(tmp_path / "a.db", on_commit=stop_at_the_fourth([]))
    with pytest.raises(KeyboardInterrupt):
        going_on.run()
    going_on.durable.on_commit = lambda: None
    going_on.run()
    stopped = _api(tmp_path / "b.db", on_commit=stop_at_the_fourth([]))
    with pytest.raises(KeyboardInterrupt):
        stopped.run()
    stopped.close()
    resumed = _api(tmp_path / "b.db", resume=True)
    assert resumed.buyer.choice is None  # (no episode of it bought: chosen again, the same)
    resumed.run()
    _same_run(going_on, resumed)
    _same_run(going_on, full)


def test_resume_after_an_iteration_reproduces_the_uninterrupted_run(tmp_path, full):
    path = tmp_path / "run.db"
    with _api(path) as first:
        first.step()
    resumed = _api(path, resume=True)
    resumed.run()
    _same_run(full, resumed)
    assert resumed.durable.closed  # a completed run releases its store


def test_one_episode_at_a_time_resumes_mid_iteration(tmp_path):
    reference = _api(rewarded_slice="episode")
    reference.run()
    path = tmp_path / "run.db"
    commits = []

    def stop_at_seventh():  # iteration 1's selection, 3 episodes and record; then 2's
        commits.append(1)
        if len(commits) == 7:
            raise KeyboardInterrupt

    first = _api(path, rewarded_slice="episode", env=_CountingChain, on_commit=stop_at_seventh)
    with pytest.raises(KeyboardInterrupt):  # episode 0 of iteration 2 bought, 1 not yet
        first.run()
    first.close()
    before = _CountingChain.measured
    resumed = _api(path, rewarded_slice="episode", env=_CountingChain, resume=True)
    assert sorted(resumed.buyer.bought) == [0]
    resumed.run()
    assert _CountingChain.measured - before == 3 * (1 + 2) * 10  # episode 1, then iteration 3
    _same_run(reference, resumed)


def test_an_existing_run_is_never_replaced_silently(tmp_path, full):
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    with pytest.raises(RunExistsError, match=r"run.db holds a run .*resume=True .*overwrite"):
        _api(path)
    assert len(RunStore.read(path).episodes[1]) == 3  # untouched
    fresh = _api(path, overwrite=True)
    assert fresh.iteration == 0 and RunStore.read(path).episodes == {}
    fresh.run()
    _same_run(full, fresh)
    missing = _api(tmp_path / "new.db", resume=True)
    assert not missing.resumed  # a resume of a missing run starts fresh
    missing.close()


@pytest.mark.parametrize(
    ("change", "name"),
    [
        ({"trials": 2}, "trials.num_trials"),
        ({"mode": "passive"}, "selection.num_repeats"),
        ({"repeats": 3}, "selection.num_repeats"),
        ({"criterion": _half_j}, "criterion"),
        ({"centers": torch.tensor([[1.0], [4.0], [5.0], [7.0], [9.0]])}, "basis.state.centers"),
        ({"tau": 2.0}, "basis."),
        ({"epsilon": 0.1}, "policy.epsilon"),
        ({"epsilon_decay": "constant"}, "policy.epsilon_decay"),
        ({"candidate_offsets": (0.0, 0.5)}, "policy.candidate_offsets"),
        ({"env": type("Other", (ChainWalkEnv,), {})}, "env.class"),
        ({"num_steps": 8}, "rewarded.num_steps"),
        ({"gamma": 0.8}, "evaluation.gamma"),
        ({"lam": 1e-2}, "evaluation.lam"),
        ({"schedule": (3, 2, 1)}, "rewarded.schedule"),
        ({"rewarded_slice": "episode"}, "rewarded.rewarded_slice"),
        ({"seed": 8}, "trials.seed"),
    ],
)
def test_a_run_of_other_settings_is_refused(tmp_path, change, name):
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    with pytest.raises(CorruptRunError, match=rf"run.db was made with other settings: .*'{name}"):
        _api(path, resume=True, **change)


def test_env_parameters_are_part_of_the_settings(tmp_path):
    """The same env class with another parameter (the env declares it): refused, named."""

    def slippery(**kw):
        return ChainWalkEnv(success_prob=0.6, **kw)

    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    with pytest.raises(CorruptRunError, match=r"other settings: \['env\.success_prob'\]"):
        _api(path, resume=True, env=slippery)


def test_a_new_public_attribute_or_a_moved_basis_module_keeps_a_run_resumable(
    tmp_path, monkeypatch, full
):
    """The identity holds the classes' names and their declared parameters only: an env that
    got a harmless new public attribute, and the basis class imported from another module path
    (as after a package reorganisation), resume the stored run."""

    def noted(**kw):
        env = ChainWalkEnv(**kw)
        env.note = "x"  # a public attribute no constructor declares
        return env

    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
        stored = api.identity
    monkeypatch.setattr(GaussianActionBasis, "__module__", "torch_api.basis")  # the old path
    resumed = _api(path, resume=True, env=noted)
    assert resumed.resumed and resumed.iteration == 1
    assert resumed.identity == stored
    assert not any("note" in key or "torch_api.basis" in str(v) for key, v in stored.items())
    resumed.run()
    _same_run(full, resumed)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"lam": 1e-2}, "evaluation.lam"),
        ({"repeats": 3}, "selection.num_repeats"),
        ({"schedule": (3, 2, 3)}, "rewarded.schedule"),
        ({"seed": 8}, "trials.seed"),
    ],
)
def test_a_changed_setting_refuses_the_resume_naming_only_its_field(tmp_path, change, field):
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    with pytest.raises(CorruptRunError, match=rf"other settings: \['{re.escape(field)}'\]$"):
        _api(path, resume=True, **change)
    _api(path, resume=True).close()  # (the stored run is untouched, and resumable as it was)


def test_device_may_change_after_a_failed_fit(tmp_path, monkeypatch):
    path = tmp_path / "run.db"
    api = _api(path, mode="passive", env=_CountingChain)

    def no_factor(matrix, lam):  # the factorisation fails, as on a rank-deficient design
        raise ValueError(f"A + λI is not positive definite (λ = {lam})")

    # (a λ small enough to fail on a few samples, below 1e-10, is refused by the constructor)
    monkeypatch.setattr(torch_api.core.solve, "_cholesky", no_factor)
    with pytest.raises(ValueError, match="not positive definite"):
        api.run()  # bought, then the fit fails
    api.close()
    monkeypatch.undo()
    assert len(RunStore.read(path).episodes[1]) == 3  # the bought rewards are stored
    before = _CountingChain.measured
    resumed = _api(path, mode="passive", resume=True, device="cpu", env=_CountingChain)
    assert resumed.buyer.pending is not None
    resumed.run()
    assert _CountingChain.measured - before == 3 * (2 + 2) * 10  # iteration 1 not bought again
    reference = _api(mode="passive")
    reference.run()
    _same_run(reference, resumed)
    assert resumed.rewarded_transitions == (3 + 2 + 2) * 10


def test_a_second_process_on_the_same_run_is_refused_naming_the_holder(tmp_path):
    path = tmp_path / "run.db"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
                import sys, time
                from torch_api.runs.store import RunStore
                store = RunStore({str(path)!r}, config={{}})
                print("holding", flush=True)
                sys.stdin.readline()
            """),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )
    try:
        assert holder.stdout.readline().strip() == "holding"
        with pytest.raises(RunInUseError, match=rf"run.db is in use .*pid {holder.pid} on host"):
            _api(path)
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    _api(path, resume=True).close()  # the holder's end frees the run


def test_a_second_writer_in_the_same_process_is_refused(tmp_path):
    path = tmp_path / "run.db"
    first = _api(path)
    with pytest.raises(RunInUseError, match=f"pid {os.getpid()}"):
        _api(path, resume=True)
    first.close()


@pytest.mark.parametrize("link", ["run.db", "run.db-wal", "run.db.lock"])
def test_writes_never_follow_a_symlink(tmp_path, link):
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    (tmp_path / link).symlink_to(target)
    with pytest.raises(StoreWriteError, match="symbolic link"):
        _api(tmp_path / "run.db")
    assert target.read_text() == "keep me"
    assert (tmp_path / link).is_symlink()


@pytest.mark.parametrize("place", ["directory at the path", "parent is a file"])
def test_an_unwritable_place_is_refused_before_anything_is_bought(tmp_path, place):
    path = tmp_path / "run.db"
    if place == "directory at the path":
        path.mkdir()
    else:
        (tmp_path / "file").write_text("")
        path = tmp_path / "file" / "run.db"
    _CountingChain.measured = 0
    with pytest.raises(StoreWriteError, match=str(path.parent if "parent" in place else path)):
        _api(path, env=_CountingChain)
    assert _CountingChain.measured == 0


_READ_ONLY_CHECK = """
import sys
sys.path.insert(0, {tests!r})
from test_checkpoint import _CountingChain, _api
from torch_api.runs.store import StoreWriteError
try:
    _api({path!r}, env=_CountingChain)
except StoreWriteError as error:
    print("REFUSED", _CountingChain.measured, error)
"""


def test_a_read_only_directory_is_refused_before_anything_is_bought(tmp_path):
    """chmod 0o500 for an ordinary user; for root (who may write there anyway) a read-only bind
    mount in a private mount namespace (``unshare -m``), gone with the process."""
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o500)
    script = _READ_ONLY_CHECK.format(tests=str(ROOT / "tests"), path=str(ro / "run.db"))
    command = [sys.executable, "-c", script]
    if os.access(ro, os.W_OK):  # root
        if shutil.which("unshare") is None:
            pytest.skip("root without unshare: no way to make a folder read-only here")
        mount = f'mount --bind -o ro {ro} {ro} && exec {sys.executable} -c "$0"'
        command = ["unshare", "-m", "sh", "-c", mount, script]
    try:
        done = subprocess.run(
            command,
            capture_output=True,
            text=True,
            env=dict(os.environ, PYTHONPATH=str(ROOT)),
            timeout=300,
        )
    finally:
        os.chmod(ro, 0o700)
    if "mount" in done.stderr and "REFUSED" not in done.stdout:
        pytest.skip(f"no read-only bind mount here: {done.stderr.strip()[-200:]}")
    line = [x for x in done.stdout.splitlines() if x.startswith("REFUSED")]
    assert line, done.stdout[-2000:] + done.stderr[-2000:]
    assert line[0].startswith(f"REFUSED 0 cannot write the run {ro / 'run.db'}")
    assert os.listdir(ro) == []


def test_a_full_disk_is_one_clear_line_and_keeps_what_was_stored(tmp_path):
    """A file-size limit (RLIMIT_FSIZE) stands in for a full disk: writes fail with EFBIG."""
    path = tmp_path / "run.db"
    script = textwrap.dedent(f"""
        import resource, signal, sys
        sys.path.insert(0, {str(ROOT / "tests")!r})
        from test_checkpoint import _api
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        api = _api({str(path)!r})
        api.step()
        api.close()
        api = _api({str(path)!r}, resume=True)
        size = sum(p.stat().st_size for p in api.durable.path.parent.iterdir())
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
        try:
            api.run()
        except Exception as error:
            print("ERROR", type(error).__name__, error)
    """)
    out = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
        timeout=300,
    )
    line = [x for x in out.stdout.splitlines() if x.startswith("ERROR")]
    assert line, out.stderr[-2000:]
    assert line[0].startswith(f"ERROR StoreWriteError cannot write the run {path}: ")
    assert len(RunStore.read(path).episodes[1]) == 3  # iteration 1 survives
    left = {p.name for p in tmp_path.iterdir()}  # the log holds committed rows: it stays
    assert left <= {"run.db", "run.db-wal", "run.db-shm", "run.db.lock", "run.db.commits"}, left


def _flip(path: Path, offset: int, bit: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 1 << bit
    path.write_bytes(bytes(data))


def test_flipped_bytes_are_refused_or_change_nothing(tmp_path):
    """Flip one bit at 200 places spread over the file: each load is refused (naming the path,
    never suggesting weights_only) or, where the bit lies in unused space, gives the very same
    run; never another one. Refused loads leave the object as it was."""
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
        api.buy()
    good = path.read_bytes()
    reference = _api()
    reference.load(path)
    refused = same = 0
    tries = 200
    for i in range(tries):
        offset = (i * 7919) % len(good)
        path.write_bytes(good)
        _flip(path, offset, i % 8)
        target = _api()
        try:
            target.load(path)
        except CorruptRunError as error:
            assert str(path) in str(error) and "weights_only" not in str(error)
            assert target.iteration == 0 and len(target.rewarded) == 0
            refused += 1
            continue
        assert target.iteration == reference.iteration
        assert torch.equal(target.theta, reference.theta)
        ea, eb = target.rewarded.episodes(), reference.rewarded.episodes()
        for key in ea.keys(True, True):
            assert torch.equal(ea[key], eb[key])
        assert target.buyer.pending.chosen.tolist() == reference.buyer.pending.chosen.tolist()
        same += 1
    print(f"{refused} of {tries} flips refused, {same} in unused bytes changed nothing")
    assert refused + same == tries and refused > 0


def test_flipped_payload_bytes_are_always_refused(tmp_path):
    """Every bit of a stored episode's bytes is covered by its checksum."""
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    db = sqlite3.connect(path)
    blob = db.execute("SELECT value FROM episode WHERE iteration = 1 AND episode = 1").fetchone()
    db.close()
    good = path.read_bytes()
    start = good.index(blob[0][:64])
    for k in range(0, len(blob[0]), max(1, len(blob[0]) // 40)):
        path.write_bytes(good)
        _flip(path, start + k, k % 8)
        with pytest.raises(CorruptRunError, match=str(path)):
            _api().load(path)


@pytest.mark.parametrize("cut", [0.1, 0.5, 0.9])
def test_truncated_file_is_refused_and_leaves_state_alone(tmp_path, cut):
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut)])
    fresh = _api()
    with pytest.raises(CorruptRunError, match=str(path)):
        fresh.load(path)
    assert fresh.iteration == 0 and len(fresh.rewarded) == 0


class _Payload:
    def __reduce__(self):
        return (Path.write_text, (Path(os.environ["PAYLOAD_MARK"]), "code ran"))


def test_a_pickle_at_the_path_is_refused_and_never_run(tmp_path, monkeypatch):
    mark = tmp_path / "mark"
    monkeypatch.setenv("PAYLOAD_MARK", str(mark))
    path = tmp_path / "run.db"
    torch.save({"format": 2, "evil": _Payload()}, path, pickle_module=pickle)
    with pytest.raises(CorruptRunError, match=str(path)) as info:
        _api().load(path)
    assert "weights_only" not in str(info.value)
    with pytest.raises(RunExistsError):
        _api(path)  # not a run, but not ours to replace either
    with pytest.raises(CorruptRunError, match=str(path)):
        _api(path, resume=True)
    assert not mark.exists()


def _tamper(path: Path, sql: str, *args) -> None:
    db = sqlite3.connect(path)
    db.execute(sql, args)
    db.commit()
    db.close()


@pytest.mark.parametrize(
    "sql",
    [
        "DROP TABLE selection",
        "DELETE FROM meta WHERE key = 'config'",
        "UPDATE meta SET value = x'7b7b' WHERE key = 'format'",  # not JSON
        "UPDATE record SET iteration = 5",
        "DELETE FROM episode WHERE episode = 1",
        "UPDATE episode SET value = x'ffffffffffffffff00'",  # a header larger than the blob
    ],
)
def test_malformed_content_is_refused_naming_the_path(tmp_path, sql):
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    _tamper(path, sql)
    fresh = _api()
    with pytest.raises(CorruptRunError, match=str(path)) as info:
        fresh.load(path)
    assert "weights_only" not in str(info.value)
    assert fresh.iteration == 0 and len(fresh.rewarded) == 0


def test_tampered_rows_with_recomputed_digests_are_still_bounded(tmp_path):
    """A blob that claims a huge tensor is refused before anything that size is built."""
    from torch_api.runs.store import _digest

    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    header = b'{"batch_size": [3, 10], "leaves": [{"key": ["x"], "dtype": "float64", '
    header += b'"shape": [1000000000000], "offset": 0}]}'
    blob = len(header).to_bytes(8, "little") + header
    _tamper(
        path,
        "UPDATE episode SET value = ?, digest = ? WHERE iteration = 1 AND episode = 0",
        blob,
        _digest("episode", (1, 0), blob),
    )
    with pytest.raises(CorruptRunError, match="outside"):
        _api().load(path)


class _NanChain(ChainWalkEnv):
    """Measures NaN in episode 1 of trial 2 of iteration 2's rewarded batch (while broken)."""

    broken = True

    def _step(self, td):
        out = super()._step(td)
        if self.broken and self.batch_size[0] == 3 * 2:  # rewarded env: T = 3 trials, M_2 = 2
            out["reward"][2 * 2 + 1] = math.nan
        return out


def test_one_bad_reward_is_named_and_the_valid_episodes_are_stored(tmp_path):
    path = tmp_path / "run.db"
    api = _api(path, env=_NanChain)
    api.step()
    with pytest.raises(ValueError, match=r"iteration 2: episode 1 of trial 2: rewards must be"):
        api.step()
    api.close()
    stored = RunStore.read(path)
    assert sorted(stored.episodes[2]) == [0]  # episode 0 of every trial is kept
    _NanChain.broken = False
    resumed = _api(path, resume=True, env=_NanChain)  # a repaired env buys episode 1 again
    assert sorted(resumed.buyer.bought) == [0]
    resumed.run()
    assert resumed.rewarded_transitions == (3 + 2 + 2) * 10


def test_env_fault_while_buying_keeps_earlier_rewards_and_names_the_failure(tmp_path, full):
    class Faulty(ChainWalkEnv):
        steps = 0
        broken = True

        def _step(self, td):
            if self.broken and self.batch_size[0] == 3 * 2:
                type(self).steps += 1
                if type(self).steps == 3:
                    raise OSError("arm controller stopped responding")
            return super()._step(td)

    path = tmp_path / "run.db"
    api = _api(path, env=Faulty)
    api.step()
    with pytest.raises(RuntimeError, match="iteration 2 failed: OSError: arm controller") as info:
        api.step()
    assert "The 3 episodes bought before (per trial) are kept" in str(info.value)
    api.close()
    Faulty.broken = False
    resumed = _api(path, resume=True, env=Faulty)  # the same robot, repaired
    assert len(resumed.rewarded) == 3 and resumed.iteration == 1
    resumed.run()
    _same_run(full, resumed)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_steps": 2.5}, r"rewarded.num_steps must be an integer, got 2.5"),
        ({"schedule": (2.7, 1.9)}, r"rewarded.schedule\[0\] must be an integer, got 2.7"),
        ({"schedule": (True, 2)}, r"rewarded.schedule\[0\] must be an integer, got True"),
        ({"lam": math.nan}, "evaluation.lam must be finite, got nan"),
        ({"lam": math.inf}, "evaluation.lam must be finite, got inf"),
        ({"knn_k": 2.5}, "evaluation.knn_k must be an integer, got 2.5"),
    ],
)
def test_non_integer_counts_and_bad_lambda_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        _api(**kwargs)


def test_a_huge_lambda_warns():
    with pytest.warns(RuntimeWarning, match="lam = 1e\\+308 is huge"):
        _api(lam=1e308)


def test_nan_sampling_probabilities_are_refused():
    from torch_api.collection import collect_episodes
    from torch_api.data import EpisodeBuffer
    from torch_api.policies import LinearQPolicy

    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    policy = LinearQPolicy(basis=basis, theta=torch.ones(basis.num_features), epsilon=0.1)
    episodes = collect_episodes(
        ChainWalkEnv(batch_size=2, seed=0), policy, num_episodes=2, num_steps=3, rewarded=True
    )
    probs = episodes["sample_probs"].clone()
    probs[0, 1] = torch.tensor([math.nan, 1.0], dtype=torch.float64)  # [nan, 1]
    episodes["sample_probs"] = probs
    with pytest.raises(ValueError, match="sample_probs rows must be probabilities"):
        EpisodeBuffer(rewarded=True, capacity=4).extend(episodes)


def test_a_pickle_inside_a_row_is_refused_and_never_run(tmp_path, monkeypatch):
    """Even with a matching checksum (anyone who can write the file can compute one), a row
    holding a pickle is refused by the decoder and its code never runs."""
    from torch_api.runs.store import _digest

    mark = tmp_path / "mark"
    monkeypatch.setenv("PAYLOAD_MARK", str(mark))
    path = tmp_path / "run.db"
    with _api(path) as api:
        api.step()
    blob = pickle.dumps(_Payload())
    _tamper(
        path,
        "UPDATE episode SET value = ?, digest = ? WHERE iteration = 1 AND episode = 0",
        blob,
        _digest("episode", (1, 0), blob),
    )
    with pytest.raises(CorruptRunError, match=str(path)) as info:
        _api().load(path)
    assert "weights_only" not in str(info.value)
    assert not mark.exists()


@pytest.fixture
def python_sigint():
    """SIGINT handled by Python (KeyboardInterrupt) during the test, whatever the process was
    started with: a background job of a non-interactive shell (``pytest &``, ``nohup``) starts
    with SIGINT ignored, and an ignored signal is never delivered."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


@pytest.mark.usefixtures("python_sigint")
def test_a_signal_whose_handler_runs_right_after_a_commit_is_no_write_error(tmp_path):
    """A SIGINT that reached Python just before a transaction began (the OS-level mask of
    ``signals_held`` only holds later ones) runs its handler at the first bytecode after COMMIT.
    The rows are committed and the interrupt goes on as one; it was a ``StoreWriteError``
    ("cannot rollback - no transaction is active", exit 1 instead of 130: seen in a test run)."""
    path = tmp_path / "run.db"
    store = RunStore(path, config={})

    class InterruptAfterCommit:  # the real connection; the interrupt lands after COMMIT
        def __init__(self, db):
            self.db = db

        def execute(self, sql, *args):
            result = self.db.execute(sql, *args)
            if sql == "COMMIT":
                _thread.interrupt_main()  # SIGINT at the Python level, as a pending handler
            return result

        def __getattr__(self, name):
            return getattr(self.db, name)

    connection = store._db
    store._db = InterruptAfterCommit(connection)
    with pytest.raises(KeyboardInterrupt):
        store.put_record(1, {"iteration": 1})
    store._db = connection
    store.close()
    assert RunStore.read(path).records == {1: {"iteration": 1}}


def test_a_stored_count_of_all_trials_reads_back_as_each_trials_share():
    """Runs stored before the counts were per trial hold one total of all trials: read back as
    its even share per trial (what those runs reported); a per-trial list reads back as is."""
    from torch_api.loop.records import per_trial_count

    assert per_trial_count(120, (3,)).tolist() == [40, 40, 40]
    assert per_trial_count([30, 50, 40], (3,)).tolist() == [30, 50, 40]
    assert per_trial_count(7, ()).tolist() == 7


@pytest.mark.usefixtures("python_sigint")
def test_an_interrupt_while_the_handlers_are_restored_leaves_no_signal_blocked(monkeypatch):
    """A signal pending at the end of a held block can run its handler while ``signals_held``
    puts the handlers back (``signal.signal`` runs pending handlers first): SIGINT's own handler
    raises KeyboardInterrupt there. The main thread's signal mask must be restored anyway; it
    was left blocking SIGINT and SIGTERM for the rest of the process, so a later interrupt was
    never delivered."""
    from torch_api.runs import run_guard

    real, calls = signal.signal, []
    expected = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)

    def restoring(sig, handler):
        calls.append(sig)
        if len(calls) == 4:  # putting SIGTERM's back, SIGINT's (restored) pending handler runs
            raise KeyboardInterrupt  # before the change, as CPython's signal.signal does
        return real(sig, handler)

    monkeypatch.setattr(run_guard.signal, "signal", restoring)
    try:
        with pytest.raises(KeyboardInterrupt), run_guard.signals_held():
            pass
    finally:
        monkeypatch.undo()
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
        handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT, signal.SIGTERM])
        signal.signal(signal.SIGINT, expected[0])
        signal.signal(signal.SIGTERM, expected[1])
    assert signal.SIGINT not in blocked and signal.SIGTERM not in blocked
    assert handlers == expected  # both put back


def test_a_durable_runs_own_settings_are_plain_values():
    """The caller's settings go into the stored identity: a list or an object is refused."""
    for bad in ({"test_steps": [1, 2]}, {"test": object()}, {3: 1}):
        with pytest.raises(ValueError, match="settings must map names to numbers"):
            DurableRun(None, settings=bad)
