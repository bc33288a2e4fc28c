"""docs/tutorial.md's code blocks run, in order, in one namespace."""

import re
from pathlib import Path

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"


def test_tutorial_code_runs(capsys) -> None:
    blocks = re.findall(r"```python\n(.*?)```", TUTORIAL.read_text(), flags=re.S)
    assert len(blocks) >= 7
    namespace: dict = {"__name__": "tutorial"}
    for i, block in enumerate(blocks):
        code = compile(block, f"{TUTORIAL.name}[block {i + 1}]", "exec")
        exec(code, namespace)  # noqa: S102 - the tutorial is our own file
    out = capsys.readouterr()
    assert "robust:" in out.out and "iteration= 0" in out.err
