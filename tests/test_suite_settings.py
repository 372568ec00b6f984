"""The suite's own guards: every test has a time bound, and CI runs Hypothesis
derandomized (tests/conftest.py, .ci/run)."""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest
from conftest import CI_MAX_EXAMPLES, PROFILE_ENV, slow_tests
from hypothesis import settings


def test_every_test_has_a_timeout(request: pytest.FixtureRequest) -> None:
    assert request.config.pluginmanager.hasplugin("timeout")
    assert float(request.config.getini("timeout")) == 300.0


def test_the_ci_profile_is_derandomized_and_bounded() -> None:
    ci = settings.get_profile("ci")
    assert ci.derandomize is True and ci.database is None
    assert ci.max_examples == CI_MAX_EXAMPLES and ci.deadline is None


def test_the_profile_follows_the_environment() -> None:
    wanted = os.environ.get(PROFILE_ENV, "dev")
    assert settings.default.derandomize is (wanted == "ci")


def test_every_line_of_the_slow_list_names_a_test() -> None:
    """A renamed or removed test must leave tests/slow.txt too: a stale line would
    let its successor run in the first tier unnoticed."""
    here = Path(__file__).parent
    for entry in sorted(slow_tests()):
        path, _, name = entry.partition("::")
        file = here.parent / path
        assert file.is_file(), entry
        tree = ast.parse(file.read_text(encoding="utf-8"))
        names = {
            n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
        }
        assert name.split("[", 1)[0] in names, entry
