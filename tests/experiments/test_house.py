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
    assert m["config_kinds"] == {"code": 2, "docstrings": 0, "comments": 0, "blank": 0}
    assert dict(m["reads"]["rollouts"]) == {"recipes/loop.py": 2}
    assert dict(m["reads"]["gamma"]) == {"recipes/loop.py": 1}
    assert m["syspath"] == ["benchmarks/bench.py:3"]
    assert m["largest"]["recipes"] == ("recipes/loop.py", 4)
    assert m["longest"]["recipes"] == ("recipes/loop.py:run", 4)
    assert m["largest"]["benchmarks"] == ("benchmarks/bench.py", 3)


def test_lines_of_code_leave_out_docstrings_comments_and_blank_lines():
    source = (
        '"""A module docstring\n'  # 1: docstring
        'of two lines."""\n'  # 2: docstring
        "\n"  # 3: blank
        "# a comment\n"  # 4: comment
        "X = 1  # code with a comment\n"  # 5: code
        "\n"  # 6: blank
        "class A:\n"  # 7: code
        '    """A class docstring."""\n'  # 8: docstring
        "\n"  # 9: blank
        "    def f(self):\n"  # 10: code
        '        """A function docstring\n'  # 11: docstring
        "\n"  # 12: docstring (a blank line inside it)
        "        # not a comment: inside the docstring\n"  # 13: docstring
        '        """\n'  # 14: docstring
        '        s = """a string that is no docstring\n'  # 15: code
        '        # nor is this a comment"""\n'  # 16: code
        "        return s\n"  # 17: code
        "\n"  # 18: blank
        "def g():\n"  # 19: code
        "    x = 1\n"  # 20: code
        '    """a string after the first statement is no docstring"""\n'  # 21: code
        "    return x\n"  # 22: code
    )
    kinds = _house().line_kinds(source)
    assert kinds == {"code": 10, "docstrings": 7, "comments": 1, "blank": 4}
    assert sum(kinds.values()) == 22
