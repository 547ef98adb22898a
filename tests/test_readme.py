"""The README's API tour runs as written."""

import re
from pathlib import Path


def test_api_tour_runs():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    tour = text[text.index("## API tour"):]
    code = re.search(r"```python\n(.*?)```", tour, re.S).group(1)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert float(namespace["reward"]) == 1.0
    assert namespace["nb"].idx.shape == (namespace["data"].size, 20)
    assert namespace["v"].shape == (5,)
