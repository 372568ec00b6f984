"""Suite-wide settings.

Hypothesis profiles, chosen by ``AWAREMW_HYPOTHESIS_PROFILE`` (``.ci/run`` sets
``ci``):

* ``dev`` (default): Hypothesis's defaults -- random examples, a local example
  database, so a failure found once is replayed first next time;
* ``ci``: derandomized (the same examples on every run: a CI failure is a real
  regression, reproducible locally with the same profile), ``CI_MAX_EXAMPLES``
  examples per test unless the test sets its own (bounded) ``max_examples``,
  no example database, no deadline (shared CI machines are slow), and the
  failing example printed for reproduction.

Two tiers: the tests named in ``tests/slow.txt`` (and those marked in the code)
are ``slow``; the README's test command runs the others, CI both.

``AWAREMW_EXPECT_COMPILED=1`` (``.ci/run``'s run against the compiled build of
``setup.py``): the session stops at once unless the ``awaremw`` imported is that
build, so a suite meant for the compiled modules never quietly tests the sources.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import settings

import awaremw

PROFILE_ENV = "AWAREMW_HYPOTHESIS_PROFILE"
SLOW_LIST = Path(__file__).with_name("slow.txt")
CI_MAX_EXAMPLES = 200

settings.register_profile("dev", settings())
settings.register_profile(
    "ci",
    derandomize=True,
    max_examples=CI_MAX_EXAMPLES,
    database=None,
    deadline=None,
    print_blob=True,
)
settings.load_profile(os.environ.get(PROFILE_ENV, "dev"))


def pytest_sessionstart(session: pytest.Session) -> None:
    # What runs keep (gateway versions, the embedded broker's account and retained
    # messages, demo summaries) goes to a directory of this session, never to the
    # user's ~/.local/state: tests start clean and leave nothing behind.
    os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="awaremw-test-state-")
    if os.environ.get("AWAREMW_EXPECT_COMPILED") == "1" and not awaremw.compiled_modules():
        raise pytest.UsageError(
            f"AWAREMW_EXPECT_COMPILED=1 but {awaremw.__file__} has no compiled module: "
            "install with AWAREMW_USE_MYPYC=1 (setup.py) and run pytest outside the checkout"
        )


def pytest_sessionfinish(session: pytest.Session) -> None:
    shutil.rmtree(os.environ["XDG_STATE_HOME"], ignore_errors=True)


def slow_tests() -> set[str]:
    """The node ids (or test functions) of ``tests/slow.txt``."""
    lines = SLOW_LIST.read_text(encoding="utf-8").splitlines()
    return {ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The second tier is marked ``slow``. ``@pytest.mark.pure_python`` tests patch a
    module's internals (or build an object without its constructor), which the
    compiled build binds at compile time: they are skipped there, said so."""
    slow = slow_tests()
    for item in items:
        nodeid = item.nodeid.replace("\\", "/")
        if nodeid in slow or nodeid.split("[", 1)[0] in slow:
            item.add_marker(pytest.mark.slow)
    if not awaremw.compiled_modules():
        return
    skip = pytest.mark.skip(reason="patches internals the compiled build binds at compile time")
    for item in items:
        if item.get_closest_marker("pure_python") is not None:
            item.add_marker(skip)
