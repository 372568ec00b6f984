"""The shipped deployments (``*.toml``), installed as the package ``awaremw.deployments``.

This folder is mapped into the package by pyproject.toml (``package-dir``), so
``pip install .`` and ``pip install -e .`` both find the files by name
(``awaremw fleet romeo4r``). The format: docs/deployments.md.
"""
