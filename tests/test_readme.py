"""The README's API tour runs as written."""

import re
import tomllib
from pathlib import Path

import lazyq_jax


def test_api_tour_runs():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    tour = text[text.index("## API tour"):]
    code = re.search(r"```python\n(.*?)```", tour, re.S).group(1)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert float(namespace["reward"]) == 1.0
    assert namespace["nb"].idx.shape == (namespace["data"].size, 20)
    assert namespace["v"].shape == (5,)


def test_the_version_is_the_packages():
    """pyproject.toml's version (what pip installs) is the package's ``__version__``."""
    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    assert project["version"] == lazyq_jax.__version__
    assert project["scripts"]["lazyq"] == "lazyq_jax.cli:main"
