"""docs/tutorial.md's code blocks run, in order, in one namespace."""

import re
from pathlib import Path

import numpy as np

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


def test_readme_example_runs(capsys) -> None:
    readme = TUTORIAL.parents[1] / "README.md"
    (block,) = re.findall(r"```python\n(.*?)```", readme.read_text(), flags=re.S)
    namespace: dict = {"__name__": "readme"}
    exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102 - our own file
    est = namespace["opt"].vertex(0).estimate
    np.testing.assert_allclose(est, [1.0, 2.0, 1.0], atol=1e-6)
