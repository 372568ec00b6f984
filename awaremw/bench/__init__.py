"""Benchmarks behind ``awaremw bench NAME``.

Each benchmark is a module ``awaremw.bench.<name>`` exposing
``add_arguments(parser: argparse.ArgumentParser) -> None`` and
``run(args: argparse.Namespace) -> dict[str, object]``; the CLI prints the
dict as one JSON object with ``--json``, or as a table otherwise. Register the
name here.
"""

BENCHMARKS: dict[str, str] = {
    "scale": "awaremw.bench.scale",
    "virtual": "awaremw.bench.virtual",
    "aggregation": "awaremw.bench.aggregation",
    "dissemination": "awaremw.bench.dissemination",
    "bridge": "awaremw.bench.bridge",
    "mac": "awaremw.bench.mac",
    "noise": "awaremw.bench.noise",
    "links": "awaremw.bench.links",
}
