"""A bad deployment file is a clear error on every verb that takes one: exit
status 2 and one line naming the file, the entry and why -- never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from awaremw.cli import main
from awaremw.protocol.config import MiddlewareConfig

NODE = '[[nodes]]\nid = 1\nkind = "gateway"\nposition = [1, 1]\n'
BAD = {
    "syntax": ("area = [10, 10\n", "invalid TOML"),
    "type": ("area = [10, 10]\n" + NODE + 'boot_s = "x"\n', "(id 1): 'boot_s' must be a number"),
    "kind": ('area = [10, 10]\n[[nodes]]\nid = 1\nkind = "drone"\nposition = [1, 1]\n',
             "unknown kind 'drone'"),
    "world": ("area = [10, 10]\n[world]\nfires = 3\n" + NODE, "fires"),
    "middleware": ('area = [10, 10]\n[middleware]\nhello_period = "x"\n' + NODE,
                   "node 1: middleware setting 'hello_period': must be a number, got 'x'"),
    "noise": ("area = [10, 10]\n" + NODE + "noise = 3\n", "node 1: 'noise' must be a table"),
    "binary": (b"\xff\xfe", "not UTF-8"),
}  # fmt: skip
VERBS = {
    "fleet": ["fleet", "{}", "--duration", "0.5"],
    "gateway": ["gateway", "{}"],
    "demo": ["demo", "--deployment", "{}", "--plain", "--duration", "1"],
    "experiment": ["experiment", "romeo4r", "--virtual", "--deployment", "{}", "--out", "out"],
}


@pytest.mark.parametrize("verb", sorted(VERBS))
@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_file_is_one_clear_line(
    case: str,
    verb: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    text, why = BAD[case]
    path = tmp_path / f"{case}.toml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    code = main([a.format(path) for a in VERBS[verb]])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith(f"awaremw {verb}: {path}") and why in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_middleware_overrides_are_type_checked() -> None:
    c = MiddlewareConfig().with_overrides({"hello_period": 2, "drip_k": 3, "is_root": True})
    assert (c.hello_period, c.drip_k, c.is_root) == (2.0, 3, True)
    for key, value, why in (
        ("drip_k", 2.5, "must be an integer, got 2.5"),
        ("drip_k", True, "must be an integer, got True"),
        ("is_root", 1, "must be true or false, got 1"),
        ("check_period", "1", "must be a number, got '1'"),
    ):
        with pytest.raises(ValueError, match=f"^middleware setting '{key}': {why}$"):
            MiddlewareConfig().with_overrides({key: value})
    with pytest.raises(ValueError, match="unknown middleware settings: nope"):
        MiddlewareConfig().with_overrides({"nope": 1})
