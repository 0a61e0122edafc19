"""Every ``>>>`` example in the library's docstrings runs and prints what it shows.

The modules are found by their source, so an example added to any module of ``tocabi_torchrl`` is run here without
being listed; a module is imported only when its source holds an example (optional integrations stay unimported).
"""
import doctest
import importlib
from pathlib import Path

import pytest

import tocabi_torchrl

PACKAGE = Path(tocabi_torchrl.__file__).parent


def _modules_with_examples() -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if ">>> " not in path.read_text(encoding="utf-8"):
            continue
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


MODULES = _modules_with_examples()


def test_the_library_has_docstring_examples_to_run():
    # An empty list would make the test below pass vacuously (a moved package, a changed marker).
    assert "tocabi_torchrl.envs.tocabi_walk" in MODULES and len(MODULES) >= 10, MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = [t for t in finder.find(module, name) if t.examples]
    assert tests, f"{name}'s source has '>>> ' but doctest finds no example in its docstrings"
    failures = []
    for test in tests:
        result = runner.run(test, out=failures.append)
        assert result.attempted
    assert not runner.failures, f"{name}: {runner.failures} docstring example(s) failed:\n" + "".join(failures)
