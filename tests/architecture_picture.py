"""Draws docs/img/architecture.png from the source: the package's floors, protocol
at the bottom and cli at the top, each module a box as wide as its lines, and
beside each floor the floors it imports from.

    python tests/architecture_picture.py

The picture carries its structure (modules per floor, floors imported) as PNG
text; tests/test_architecture.py reads it back and fails when the code has
moved on, so the picture in docs/architecture.md stays true.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_architecture import LAYERS, ROOT, graph, modules, rank

PICTURE = ROOT.parent / "docs" / "img" / "architecture.png"
KEY = "awaremw-structure"


def short(name: str) -> str:
    """A module's name inside its floor ('' for the floor's package)."""
    return name.split(".", 2)[-1] if name.count(".") > 1 else ""


def structure() -> dict[str, dict[str, list[str]]]:
    """Per floor: its modules (short names) and the floors it imports from."""
    g = graph(ROOT)
    floors: dict[str, dict[str, list[str]]] = {f: {"modules": [], "imports": []} for f in LAYERS}
    for name in sorted(modules(ROOT)):
        r = rank(name)
        if r < 0:
            continue
        floor = LAYERS[r]
        floors[floor]["modules"].append(short(name))
        below = {LAYERS[rank(d)] for d in g[name] if 0 <= rank(d) < r}
        floors[floor]["imports"] = sorted(set(floors[floor]["imports"]) | below, key=LAYERS.index)
    return floors


def draw(path: Path = PICTURE) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    s = structure()
    files = modules(ROOT)
    lines: dict[str, dict[str, int]] = {f: {} for f in LAYERS}
    for name, p in files.items():
        if rank(name) >= 0:
            lines[LAYERS[rank(name)]][short(name)] = len(p.read_text(encoding="utf-8").splitlines())
    widest = max(sum(v.values()) for v in lines.values())
    width, gap = 10.0, 0.04
    fig, ax = plt.subplots(figsize=(15, 0.75 * len(LAYERS) + 0.6))
    for y, floor in enumerate(LAYERS):
        ax.text(-0.15, y + 0.4, floor, ha="right", va="center", fontsize=11, weight="bold")
        x = 0.0
        for mod, n in sorted(lines[floor].items(), key=lambda kv: -kv[1]):
            w = max(width * n / widest - gap, 0.02)
            ax.add_patch(Rectangle((x, y), w, 0.8, facecolor=f"C{y % 10}", alpha=0.35,
                                   edgecolor="black", linewidth=0.5))  # fmt: skip
            label = (mod or "__init__").replace(".", "/")
            if w > 0.12 * len(label) * 0.55:
                ax.text(x + w / 2, y + 0.4, label, ha="center", va="center", fontsize=6.5)
            elif w > 0.12:  # a narrow box: its name upright, cut to the box's height
                ax.text(x + w / 2, y + 0.4, label[:11], ha="center", va="center", fontsize=5.5,
                        rotation=90)  # fmt: skip
            x += w + gap
        deps = s[floor]["imports"]
        ax.text(width + 0.2, y + 0.4, "imports " + (", ".join(deps) if deps else "nothing"),
                ha="left", va="center", fontsize=8.5, color="0.25")  # fmt: skip
    ax.set_xlim(-1.6, width + 3.6)
    ax.set_ylim(-0.3, len(LAYERS) + 0.1)
    ax.axis("off")
    ax.set_title("awaremw: one floor a layer, every import goes down (box width = lines of code)",
                 fontsize=12)  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight", metadata={KEY: json.dumps(s)})
    plt.close(fig)


def read_structure(path: Path = PICTURE) -> dict[str, dict[str, list[str]]] | None:
    """The structure a picture was drawn from (its PNG text chunk), None if absent."""
    data = path.read_bytes()
    pos = 8
    while pos + 8 <= len(data):
        (length,), kind = struct.unpack(">I", data[pos : pos + 4]), data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"tEXt" and body.startswith(KEY.encode() + b"\0"):
            return json.loads(body.split(b"\0", 1)[1].decode("latin-1"))  # type: ignore[no-any-return]
        pos += 12 + length
    return None


if __name__ == "__main__":
    draw()
    print(f"wrote {PICTURE.relative_to(ROOT.parent)}")
