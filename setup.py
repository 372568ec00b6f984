"""The optional compiled build: the emulator's hot modules compiled with mypyc.

``pip install .`` installs pure Python (everything in pyproject.toml). With
``AWAREMW_USE_MYPYC=1`` the modules of :data:`COMPILED` are compiled to C
extensions by mypyc (part of mypy, which the test extra already installs), the
same sources, type-checked, about 1.6x faster on the virtual clock
(docs/runtime.md, "The compiled build")::

    pip install 'mypy>=1.10' 'setuptools>=70.1'   # the test extra has both
    AWAREMW_USE_MYPYC=1 pip install --no-build-isolation .

Not for an editable install: a compiled module next to its source shadows it,
so edits would silently not run. ``awaremw.build_info.compiled_modules()``
(and the ``build`` key of ``awaremw bench virtual --json``) says which
modules a process runs compiled.
"""

from __future__ import annotations

import os
import sys

from setuptools import find_packages, setup

# The protocol core, the virtual medium and its clock, the radio's link layer and
# propagation model and the world's fields: where a run spends its time. Pure
# modules with precise types (mypy --strict), nothing monkeypatched.
COMPILED = [
    "awaremw/protocol/channels.py",
    "awaremw/protocol/collection.py",
    "awaremw/protocol/commands.py",
    "awaremw/protocol/component.py",
    "awaremw/protocol/ctp_forwarding.py",
    "awaremw/protocol/ctp_routes.py",
    "awaremw/protocol/dissemination.py",
    "awaremw/protocol/drip_gossip.py",
    "awaremw/protocol/drip_items.py",
    "awaremw/protocol/drip_signed.py",
    "awaremw/protocol/events.py",
    "awaremw/protocol/groups/__init__.py",
    "awaremw/protocol/groups/conditions.py",
    "awaremw/protocol/groups/coordinator.py",
    "awaremw/protocol/groups/election.py",
    "awaremw/protocol/groups/flood.py",
    "awaremw/protocol/groups/handover.py",
    "awaremw/protocol/groups/kit.py",
    "awaremw/protocol/groups/lineage.py",
    "awaremw/protocol/groups/liveness.py",
    "awaremw/protocol/groups/merge.py",
    "awaremw/protocol/groups/pace.py",
    "awaremw/protocol/groups/roles.py",
    "awaremw/protocol/groups/standing.py",
    "awaremw/protocol/groups/tree.py",
    "awaremw/protocol/groups/values.py",
    "awaremw/protocol/mote.py",
    "awaremw/protocol/timers.py",
    "awaremw/protocol/trickle.py",
    "awaremw/radio/counters.py",
    "awaremw/radio/linklayer.py",
    "awaremw/radio/mac.py",
    "awaremw/radio/model.py",
    "awaremw/radio/neighbourhood.py",
    "awaremw/radio/noise.py",
    "awaremw/radio/reception.py",
    "awaremw/radio/virtual_medium.py",
    "awaremw/world/fields.py",
    "awaremw/world/timerq.py",
]


def _ext_modules() -> list[object]:
    if os.environ.get("AWAREMW_USE_MYPYC", "0") != "1":
        return []
    if "editable_wheel" in sys.argv or "develop" in sys.argv:
        raise SystemExit(
            "AWAREMW_USE_MYPYC=1 is for a regular install (pip install --no-build-isolation .): "
            "in an editable install the compiled modules would shadow the sources you edit"
        )
    try:
        from mypyc.build import mypycify
    except ImportError:
        raise SystemExit(
            "AWAREMW_USE_MYPYC=1 needs mypy in the build environment: "
            "pip install 'mypy>=1.10' 'setuptools>=70.1', then pip install --no-build-isolation ."
        ) from None
    return list(mypycify(COMPILED, opt_level="3", group_name="awaremw_compiled"))


# awaremw's packages, and the shipped deployments: the top-level nodes/ folder
# installed as awaremw.deployments (pyproject.toml maps the directory).
PACKAGES = [*find_packages(include=["awaremw", "awaremw.*"]), "awaremw.deployments"]

setup(packages=PACKAGES, ext_modules=_ext_modules())
