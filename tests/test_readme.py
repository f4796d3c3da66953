"""The README's Python example runs as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    assert blocks, "the README has no Python example"
    monkeypatch.chdir(tmp_path)  # the example stores its run under runs/
    for block in blocks:
        namespace: dict = {}
        exec(compile(block, str(README), "exec"), namespace)  # noqa: S102
    assert len(namespace["history"]) == 7
    assert namespace["api"].rewarded_transitions == (5 + 5 + 3 + 3 + 3 + 1 + 1) * 10
    assert (tmp_path / "runs" / "chain.db").exists()
