"""The one option validator (``link/options.py``): declared options become one-line errors
naming the key — wrong type, out of range, unknown key, vector length, missing required — for
the spec alone and through every driver."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from robid_link.exceptions import ConfigError
from robid_link.link import registry
from robid_link.link.driver import Driver
from robid_link.link.options import (
    Choice,
    File,
    Flag,
    Folder,
    Integer,
    Number,
    Options,
    Secret,
    Table,
    Text,
    Vector,
)

SPEC = Options(
    share=Folder(hint="the shared folder"),
    rate_hz=Number(100.0, above=0, high=1000), retries=Integer(3, low=0, high=10),
    mode=Choice("auto", "manual", default="auto"), rapid=Flag(True), host=Text(None),
    gains=Vector(Number(above=0), None, per_joint=True), extra=Table(None),
    password=Secret(None), version=Choice(1, 2, default=1))


def _error(given: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as err:
        SPEC.parse(given, owner="demo")
    msg = str(err.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize(("given", "message"), [
    ({"share": 5}, "driver.share: expected a folder path, got 5"),
    ({"share": "/s", "rate_hz": "fast"},
     "driver.rate_hz: expected a number in (0, 1000], got 'fast'"),
    ({"share": "/s", "rate_hz": True}, "driver.rate_hz: expected a number in (0, 1000], got True"),
    ({"share": "/s", "rate_hz": float("inf")},
     "driver.rate_hz: expected a number in (0, 1000], got inf"),
    ({"share": "/s", "retries": 2.0}, "driver.retries: expected an integer in [0, 10], got 2.0"),
    ({"share": "/s", "mode": "magic"}, "driver.mode: expected one of auto, manual, got 'magic'"),
    ({"share": "/s", "version": True}, "driver.version: expected one of 1, 2, got True"),
    ({"share": "/s", "rapid": "yes"}, "driver.rapid: expected true or false, got 'yes'"),
    ({"share": "/s", "host": ""}, "driver.host: expected a non-empty string, got ''"),
    ({"share": "/s", "extra": [1]}, "driver.extra: expected a mapping, got [1]"),
    ({"share": "/s", "gains": 3.0},
     "driver.gains: expected a list with one value per joint, each a number > 0, got 3.0"),
])
def test_wrong_type_is_one_line_naming_the_key(given: dict[str, Any], message: str) -> None:
    assert _error(given) == message


@pytest.mark.parametrize(("given", "message"), [
    ({"share": "/s", "rate_hz": 0}, "driver.rate_hz: expected a number in (0, 1000], got 0"),
    ({"share": "/s", "rate_hz": 2000}, "driver.rate_hz: expected a number in (0, 1000], got 2000"),
    ({"share": "/s", "retries": -1}, "driver.retries: expected an integer in [0, 10], got -1"),
    ({"share": "/s", "gains": [1.0, -2.0]},
     "driver.gains[1]: expected a number > 0, got -2.0"),
])
def test_out_of_range_names_the_key_and_the_bounds(given: dict[str, Any], message: str) -> None:
    assert _error(given) == message


def test_unknown_key_names_the_known_ones() -> None:
    assert _error({"share": "/s", "colour": 1}) == (
        "driver.colour: unknown option for driver 'demo' (known: extra, gains, host, mode, "
        "password, rapid, rate_hz, retries, share, version)")


def test_missing_required_says_what_to_give() -> None:
    assert _error({}) == "driver.share: missing (the shared folder)"
    assert _error({"share": None}) == "driver.share: missing (the shared folder)"


def test_defaults_fill_in_and_values_are_normalised() -> None:
    v = SPEC.parse({"share": "/s", "rate_hz": 50, "gains": [1, 2, 3]}, owner="demo")
    assert v.share == Path("/s") and v.rate_hz == 50.0 and isinstance(v.rate_hz, float)
    assert v.gains == (1.0, 2.0, 3.0) and v.retries == 3 and v.mode == "auto"
    assert v.host is None and v.extra is None


def test_per_joint_vectors_must_match_the_robot() -> None:
    v = SPEC.parse({"share": "/s", "gains": [1.0, 2.0]}, owner="demo")
    with pytest.raises(ConfigError, match=r"^driver\.gains: 2 values, robot arm3 has 3 "
                                          r"joints$"):
        SPEC.check_joints(v, 3, "arm3")
    SPEC.check_joints(v, 2, "arm2")
    SPEC.check_joints(SPEC.parse({"share": "/s"}, owner="demo"), 6, "arm6")  # not given


def test_a_secret_is_never_shown() -> None:
    msg = _error({"share": "/s", "password": 12345})
    assert msg == ("driver.password: expected a non-empty string, got a value of type int "
                   "(not shown: secret)")
    v = SPEC.parse({"share": "/s", "password": "hunter2"}, owner="demo")
    assert v.password == "hunter2" and "hunter2" not in repr(v) and "password=***" in repr(v)


def test_files_must_exist_and_a_private_one_be_owner_only(tmp_path: Path) -> None:
    spec = Options(eds=File(exists=True), cred=File(None, private=True))
    with pytest.raises(ConfigError, match=r"^driver\.eds: .*nope\.eds: file not found$"):
        spec.parse({"eds": str(tmp_path / "nope.eds")})
    (tmp_path / "a.eds").write_text("x")
    cred = tmp_path / "cred"
    cred.write_text("robid:pw\n")
    cred.chmod(0o640)
    with pytest.raises(ConfigError, match=r"^driver\.cred: .*cred is readable by others "
                                          r"\(mode 0640\); chmod 600 "):
        spec.parse({"eds": str(tmp_path / "a.eds"), "cred": str(cred)})
    cred.chmod(0o600)
    assert spec.parse({"eds": tmp_path / "a.eds", "cred": str(cred)}).cred == cred


def test_a_vector_without_repeats() -> None:
    spec = Options(nodes=Vector(Integer(low=1, high=127, expect="a node id in 1..127"),
                                unique=True))
    with pytest.raises(ConfigError, match=r"^driver\.nodes: expected a list without repeated "
                                          r"values, got \[1, 1\]$"):
        spec.parse({"nodes": [1, 1]})
    with pytest.raises(ConfigError, match=r"^driver\.nodes\[0\]: expected a node id in 1\.\.127, "
                                          r"got 0$"):
        spec.parse({"nodes": [0]})


def test_a_long_value_is_cut_in_the_message() -> None:
    msg = _error({"share": "/s", "host": ["x" * 500]})
    assert len(msg) < 140 and msg.endswith("…")


# -- through the drivers: every registered driver checks its options with the spec
NAMES = sorted(registry.available_drivers())


@pytest.mark.parametrize("name", NAMES)
def test_every_driver_declares_its_options(name: str) -> None:
    cls = registry.driver_class(name)
    assert isinstance(cls.options, Options) and len(cls.options) > 0


@pytest.mark.parametrize("name", NAMES)
def test_every_driver_refuses_an_unknown_key_in_one_line(name: str) -> None:
    cls = registry.driver_class(name)
    with pytest.raises(ConfigError, match=rf"^driver\.colour: unknown option for driver "
                                          rf"'{name}' \(known: "):
        cls(colour=1)  # directly too, not only through make_driver


@pytest.mark.parametrize("name", NAMES)
def test_every_driver_names_a_missing_required_option(name: str) -> None:
    cls = registry.driver_class(name)
    required = [k for k, o in cls.options.items() if o.required]  # type: ignore[union-attr]
    assert required, f"{name} requires nothing?"
    with pytest.raises(ConfigError, match=rf"^driver\.{required[0]}: missing"):
        registry.make_driver({"name": name})


def test_a_number_where_the_share_is_expected_is_one_line() -> None:
    """It used to raise TypeError from pathlib."""
    with pytest.raises(ConfigError, match=r"^driver\.share: expected a folder path, got 5$"):
        registry.make_driver({"name": "file_share", "share": 5})
    with pytest.raises(ConfigError, match=r"^driver\.share: expected a folder path, got 5$"):
        registry.make_driver({"name": "modbus_plc", "host": "plc", "share": 5})


def test_an_older_plug_in_with_a_set_of_names_still_works() -> None:
    class Legacy(Driver):
        name = "legacy"
        options = frozenset({"port"})

        def __init__(self, port: int = 1) -> None:
            super().__init__()
            self.port = port

        async def _open(self) -> None: ...
        async def _close(self) -> None: ...
        async def _put_program(self, program: Any) -> None: ...
        async def _give_ready(self, exp_id: str, nonce: str) -> None: ...
        async def _wait_done(self, exp_id: str, nonce: str) -> Any: ...
        async def _fetch_logs(self, done: Any) -> bytes: return b""

    assert Legacy(port=3).port == 3


def test_a_plug_in_shadowing_a_built_in_name_is_refused(monkeypatch):
    """A third-party entry point under a built-in's name was silently ignored: choosing the
    name now names both claims (issue 18)."""
    from importlib.metadata import EntryPoint

    eps = [EntryPoint("file_share", "my_cell.share:ShareDriver", registry.ENTRY_POINT_GROUP),
           EntryPoint("my_cell", "my_cell.drv:CellDriver", registry.ENTRY_POINT_GROUP),
           EntryPoint("serial_line", "robid_link.drivers.serial_line:SerialLineDriver",
                      registry.ENTRY_POINT_GROUP)]
    monkeypatch.setattr(registry, "entry_points", lambda group: [
        e for e in eps if e.group == group])
    table = registry.available_drivers()
    assert table["my_cell"] == "my_cell.drv:CellDriver"
    assert table["serial_line"] == "robid_link.drivers.serial_line:SerialLineDriver"  # the same
    with pytest.raises(ConfigError) as err:
        registry.driver_class("file_share")
    msg = str(err.value)
    assert msg.startswith("driver.name: driver name 'file_share' is claimed by ")
    assert "robid_link.drivers.file_share:FileShareDriver" in msg
    assert "my_cell.share:ShareDriver" in msg and "\n" not in msg
