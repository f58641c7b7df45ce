"""``benchmarks/house.py``: the house's measures on a small repository written here, counted by hand."""

from __future__ import annotations

import importlib.util
import sys

from paths import REPO


def _house():
    spec = importlib.util.spec_from_file_location("house", REPO / "benchmarks" / "house.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_measures_of_a_small_repository(tmp_path):
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "config.py").write_text("a = 1\nb = 2\n")  # 2 lines of config handling
    (tmp_path / "recipes" / "loop.py").write_text(
        "def run(cfg):\n"  # a function of 4 lines
        "    n = cfg.eval.rollouts\n"  # one read by attribute
        "    m = cfg['rollouts']\n"  # one by key
        "    return n + m + cfg.objective.gamma\n"  # one read of gamma
    )
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "bench.py").write_text(
        'import sys\n"""sys.path in a string is no use"""\nsys.path.insert(0, ".")\n'
    )
    m = _house().measure(tmp_path)
    assert m["config"] == {"recipes/config.py": 2}
    assert dict(m["reads"]["rollouts"]) == {"recipes/loop.py": 2}
    assert dict(m["reads"]["gamma"]) == {"recipes/loop.py": 1}
    assert m["syspath"] == ["benchmarks/bench.py:3"]
    assert m["largest"]["recipes"] == ("recipes/loop.py", 4)
    assert m["longest"]["recipes"] == ("recipes/loop.py:run", 4)
    assert m["largest"]["benchmarks"] == ("benchmarks/bench.py", 3)
