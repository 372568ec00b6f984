"""The suite's own guards: every test has a time bound, and CI runs Hypothesis
derandomized (tests/conftest.py, .ci/run)."""

from __future__ import annotations

import os

import pytest
from conftest import CI_MAX_EXAMPLES, PROFILE_ENV
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
