"""examples/batting_reference.py and examples/plot_batting_episode.py, ``main(argv)`` in this
process with tiny budgets: their files, and a bad value refused in one line (exit 2)."""

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import batting_reference  # noqa: E402
import plot_batting_episode  # noqa: E402


def test_batting_reference_writes_the_optimum_and_the_random_policy(tmp_path, capsys):
    out = tmp_path / "folder" / "reference.json"
    batting_reference.main(["--episodes", "16", "--out", str(out)])
    payload = json.loads(out.read_text())
    assert payload["reference_optimum"]["best_sequence"] == [0, 0, 1, 1, 1, 1, 1, 0, 0, 0]
    assert payload["reference_optimum"]["best_carry"] == pytest.approx(13.744, abs=1e-3)
    assert payload["random_policy"]["episodes"] == 16
    assert f"wrote {out}" in capsys.readouterr().out


def test_plot_batting_episode_draws_the_reference_optimum(tmp_path, capsys):
    out = tmp_path / "folder" / "episode.png"
    plot_batting_episode.main(["--sequence", "0011111000", "--out", str(out)])
    assert "carry 13.74 m" in capsys.readouterr().out
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("script", "flags", "message"),
    [
        (batting_reference, ["--episodes", "-3"], "error: episodes must be >= 1"),
        (plot_batting_episode, ["--snapshot-ms", "-3"], "error: snapshot_ms must be > 0, got -3.0"),
        (plot_batting_episode, ["--sequence", "012"], "error: sequence must be 1 to 10 digits"),
    ],
)
def test_a_bad_value_is_one_line_naming_it_exit_2(script, flags, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        script.main([*flags, "--out", str(tmp_path / "never" / "x")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.startswith(message) and len(err.splitlines()) == 1, err
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("script", [batting_reference, plot_batting_episode])
def test_an_unwritable_output_folder_or_an_unknown_flag_exits_2(script, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.raises(SystemExit) as stop:
        script.main(["--out", str(blocker / "x" / "out")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.startswith("error: ") and len(err.splitlines()) == 1
    with pytest.raises(SystemExit) as stop:
        script.main(["--trials", "1"])  # nothing here takes trials: refused by the parser
    assert stop.value.code == 2 and "--trials" in capsys.readouterr().err


@pytest.mark.parametrize("script", [batting_reference, plot_batting_episode])
def test_help_shows_every_option_with_its_docstring(script, capsys):
    with pytest.raises(SystemExit) as stop:
        script.main(["--help"])
    shown = capsys.readouterr().out
    assert stop.value.code == 0 and "--out" in shown
    assert all(f"--{name.replace('_', '-')}" in shown for name in script.Args.__dataclass_fields__)
