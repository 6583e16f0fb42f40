"""The bounded YAML loader on libyaml's parser (where PyYAML has it) and on the pure-Python one:
the same documents, the same bounds, one-line errors at the same line."""

from __future__ import annotations

from pathlib import Path

import pytest

from robid_link import safeyaml
from robid_link.exceptions import ConfigError
from robid_link.safeyaml import load_yaml

ROOT = Path(__file__).resolve().parent.parent
LOADERS = {cls.__name__: cls for cls in safeyaml._LOADERS}


@pytest.fixture(params=sorted(LOADERS))
def loader(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setattr(safeyaml, "_LOADERS", [LOADERS[request.param]])
    return str(request.param)


def _bomb(levels: int = 9) -> str:
    text = 'a0: &a0 ["x","x","x","x","x","x","x","x","x"]\n'
    for i in range(1, levels):
        text += f"a{i}: &a{i} [{','.join([f'*a{i - 1}'] * 9)}]\n"
    return text


def test_every_example_file_loads_the_same() -> None:
    files = sorted((ROOT / "examples").rglob("*.yaml"))
    assert files
    for path in files:
        docs = []
        for cls in LOADERS.values():
            saved = safeyaml._LOADERS
            safeyaml._LOADERS = [cls]
            try:
                docs.append(load_yaml(path.read_bytes(), str(path)))
            finally:
                safeyaml._LOADERS = saved
        assert all(d == docs[0] for d in docs), path


@pytest.mark.parametrize("text, message", [
    (_bomb(), r"refused YAML at line 7: more than 1000000 nodes once aliases are expanded"),
    ("a: &a [1]\nb: [" + ", ".join(["*a"] * 101) + "]\n",
     r"refused YAML at line 2: more than 100 alias references"),
    ("a:\n  b: " + "[" * 40 + "]" * 40 + "\n", r"refused YAML at line 2: nested deeper than 32"),
    # libyaml stops it first, at its own limit of 1,000 levels
    ("[" * 30_000 + "]" * 30_000,
     r"(refused|invalid) YAML at line 1: (nested deeper than 32|exceeded maximum nesting)"),
    ("a: 1\nb: [1, 2\n", r"invalid YAML at line 3: .*(expected|find) ','"),
    ("a: \x07\n", r"invalid YAML: unacceptable character #x0007"),
    ("--- 1\n--- 2\n", r"invalid YAML at line 2: but found another document"),
    ("a: 1e3\nb: -4e-06\n", None),
])
def test_bounds_and_errors(loader: str, text: str, message: str | None) -> None:
    if message is None:
        assert load_yaml(text, "x.yaml") == {"a": 1000.0, "b": -4e-06}
        return
    with pytest.raises(ConfigError, match="^x.yaml: " + message) as exc:
        load_yaml(text, "x.yaml")
    assert "\n" not in str(exc.value)


def test_libyaml_is_used_where_pyyaml_has_it() -> None:
    import yaml

    if getattr(yaml, "__with_libyaml__", False):
        assert safeyaml._LOADERS[-1].__name__ == "_BoundedCLoader"
