"""awaremw: the AWARE data-centric WSN middleware, emulated over Eclipse Zenoh.

Layers, top to bottom (each imports only from its own layer or those below
it; tests/test_architecture.py enforces it):

    cli > bench > experiments > view > gateway > nodes > runtime > radio > world > protocol

``awaremw.protocol`` is sans-IO: it never touches sockets, asyncio, clocks or
global randomness. See ``docs/architecture.md``.
"""

__version__ = "0.1.0"


def compiled_modules() -> list[str]:
    """The awaremw modules this installation runs compiled (the optional mypyc
    build of ``setup.py``), as dotted names, sorted; ``[]`` for pure Python.

    A compiled module sits next to its source and Python imports it first."""
    import importlib.machinery
    from pathlib import Path

    root = Path(__file__).resolve().parent
    suffixes = sorted(importlib.machinery.EXTENSION_SUFFIXES, key=len, reverse=True)
    out = []
    for path in root.rglob("*"):
        suffix = next((s for s in suffixes if path.name.endswith(s)), None)
        if suffix is not None:
            rel = path.relative_to(root.parent)
            out.append(".".join([*rel.parts[:-1], path.name[: -len(suffix)]]))
    return sorted(out)
