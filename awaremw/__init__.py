"""awaremw: the AWARE data-centric WSN middleware, emulated over Eclipse Zenoh.

Layers, top to bottom (each imports only from its own layer or those below
it; tests/test_architecture.py enforces it):

    cli > bench > experiments > view > gateway > nodes > runtime > radio > world > protocol

``awaremw.protocol`` is sans-IO: it never touches sockets, asyncio, clocks or
global randomness. See ``docs/architecture.md``.
"""

__version__ = "0.1.0"
