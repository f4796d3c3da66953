"""The README's Python example runs as written."""

import re
import warnings
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    assert blocks, "the README has no Python example"
    monkeypatch.chdir(tmp_path)  # the example stores its run under runs/
    with warnings.catch_warnings(record=True) as caught:
        for block in blocks:
            namespace: dict = {}
            exec(compile(block, str(README), "exec"), namespace)  # noqa: S102
    # The README's chain-walk example runs 100 trials; in a few of them an early sampling policy
    # is far from the evaluation policy and the library says so (README, Troubleshooting:
    # "importance weights collapsed"). That is the only warning the example may give.
    unexpected = [w for w in caught if "importance weights collapsed" not in str(w.message)]
    assert not unexpected, [f"{w.category.__name__}: {w.message}" for w in unexpected]
    assert len(namespace["history"]) == 7
    assert namespace["api"].rewarded_transitions == (5 + 5 + 3 + 3 + 3 + 1 + 1) * 10
    assert (tmp_path / "runs" / "chain.db").exists()
