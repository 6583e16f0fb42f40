"""YAML 1.2 floats in every file the tool reads: ``-4e-06`` is a number, not a string."""

from __future__ import annotations

from pathlib import Path

import yaml

from robid_link.safeyaml import load_yaml
from robid_link.yamlio import read_yaml_mapping


def test_exponent_floats_without_a_dot_are_numbers(tmp_path: Path) -> None:
    doc = load_yaml("a: -4e-06\nb: 1e3\nc: 1.5E-3\nd: 2\ne: name1e3\n", "x.yaml")
    assert doc == {"a": -4e-06, "b": 1000.0, "c": 0.0015, "d": 2, "e": "name1e3"}
    assert isinstance(doc["d"], int)
    p = tmp_path / "truth.yaml"
    p.write_text("noise: {tau: 3e-1, q_resolution: 6e-6}\n")
    assert read_yaml_mapping(p, "truth file")["noise"] == {"tau": 0.3, "q_resolution": 6e-6}


def test_the_plain_safe_loader_is_left_alone() -> None:
    assert yaml.safe_load("a: 1e3") == {"a": "1e3"}  # PyYAML's own resolver: unchanged
