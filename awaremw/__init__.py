"""awaremw: the AWARE data-centric WSN middleware, emulated over Eclipse Zenoh.

Layers, top to bottom (each imports only from layers below it):

    cli -> gateway -> runtime -> radio -> world -> protocol
                     nodes (application layer: node kinds, deployments)

``awaremw.protocol`` is sans-IO: it never touches sockets, asyncio, clocks or
global randomness. See ``docs/architecture.md``.
"""

__version__ = "0.1.0"
