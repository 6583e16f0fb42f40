"""Driver and fake-peer lookup: built-in tables of ``name → module:Class`` extended by the
entry-point groups ``robid_link.drivers`` and ``robid_link.fake_peers``. A module is imported
only when it is chosen, so the product never imports a driver or a fake it does not use."""

from __future__ import annotations

import importlib
import importlib.util
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any

from robid_link.exceptions import ConfigError
from robid_link.link.driver import Driver

__all__ = ["BUILTIN_DRIVERS", "BUILTIN_PEERS", "available_drivers", "available_peers",
           "driver_class", "make_driver", "peer_class", "fake_module"]

ENTRY_POINT_GROUP = "robid_link.drivers"
PEER_ENTRY_POINT_GROUP = "robid_link.fake_peers"

#: drivers shipped with robid_link → (``module:Class``, the extra that installs its library)
BUILTIN_DRIVERS: dict[str, tuple[str, str | None]] = {
    "file_share": ("robid_link.drivers.file_share:FileShareDriver", None),
    "abb_rws": ("robid_link.drivers.abb_rws:AbbRwsDriver", "rws"),
    "canopen_drives": ("robid_link.drivers.canopen.drives:CanopenDrivesDriver", "can"),
    "modbus_plc": ("robid_link.drivers.modbus_plc:ModbusPlcDriver", "modbus"),
    "serial_line": ("robid_link.drivers.serial_line:SerialLineDriver", "serial"),
    "ur_rtde": ("robid_link.drivers.ur.rtde_driver:UrRtdeDriver", None),
}

#: the fake controller side of each built-in driver's protocol (tests, demo, fake-controller)
BUILTIN_PEERS: dict[str, str] = {
    "file_share": "robid_link.fakes.file_share_peer:FileSharePeer",
    "abb_rws": "robid_link.fakes.rws.peer:RwsPeer",
    "canopen_drives": "robid_link.fakes.canopen.peer:Cia402Peer",
    "modbus_plc": "robid_link.fakes.modbus_peer:ModbusPeer",
    "serial_line": "robid_link.fakes.serial_peer:SerialPeer",
    "ur_rtde": "robid_link.fakes.ur.peer:UrRtdePeer",
}

#: fakes the product uses by name: the simulated robot and the protocol-neutral controller
FAKE_MODULES = {"plant": "robid_link.fakes.plant", "controller": "robid_link.fakes.controller"}


def _installed(builtin: dict[str, str], group: str) -> dict[str, str]:
    """The built-ins plus the group's entry points. A name claimed by two different targets
    (a plug-in shadowing a built-in, or two plug-ins) maps to every claim, joined by ' | ':
    choosing it is refused (``_load``), never silently one of them."""
    claims: dict[str, list[str]] = {name: [target] for name, target in builtin.items()}
    for ep in entry_points(group=group):
        dist = getattr(ep.dist, "name", None)
        target = ep.value if dist in (None, "robid_link", "robid-link") else f"{ep.value} ({dist})"
        if ep.value not in [c.partition(" (")[0] for c in claims.get(ep.name, [])]:
            claims.setdefault(ep.name, []).append(target)
    return {name: " | ".join(targets) for name, targets in claims.items()}


def _shipped(table: dict[str, str]) -> dict[str, str]:
    """Built-ins whose module is in this installation (a later issue's driver may not be)."""
    return {name: target for name, target in table.items()
            if importlib.util.find_spec(target.partition(":")[0]) is not None}


def available_drivers() -> dict[str, str]:
    """Every driver name → ``module:Class``: built-ins present here, then installed plug-ins."""
    return _installed(_shipped({k: v for k, (v, _) in BUILTIN_DRIVERS.items()}),
                      ENTRY_POINT_GROUP)


def available_peers() -> dict[str, str]:
    """Every fake peer by the driver name it answers."""
    return _installed(_shipped(BUILTIN_PEERS), PEER_ENTRY_POINT_GROUP)


def _load(kind: str, key: str, name: str, table: dict[str, str], extra: str | None) -> Any:
    if name not in table:
        raise ConfigError(f"{key}: unknown {kind} {name!r} "
                          f"(available: {', '.join(sorted(table))})")
    if " | " in table[name]:
        raise ConfigError(f"{key}: {kind} name {name!r} is claimed by {table[name]}: rename "
                          "the plug-in's entry point")
    module_name, _, attr = table[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        hint = f"; install it with: pip install 'robid_link[{extra}]'" if extra else ""
        raise ConfigError(f"{key}: {kind} {name!r} cannot be imported "
                          f"({err.name or err}){hint}") from err
    return getattr(module, attr, None)


def driver_class(name: str) -> type[Driver]:
    extra = BUILTIN_DRIVERS.get(name, ("", None))[1]
    cls = _load("driver", "driver.name", name, available_drivers(), extra)
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise ConfigError(f"driver.name: {available_drivers()[name]} is not a robid_link Driver")
    return cls


def peer_class(name: str) -> Any:
    """The fake peer class (a ``robid_link.fakes.controller.Peer``) for driver ``name``."""
    extra = BUILTIN_DRIVERS.get(name, ("", None))[1]
    cls = _load("fake peer", "--driver", name, available_peers(), extra)
    if not isinstance(cls, type):
        raise ConfigError(f"--driver: {available_peers()[name]} is not a fake peer class")
    return cls


def fake_module(name: str) -> ModuleType:
    """A fake the product uses by name (``plant``, ``controller``), imported on demand."""
    module: ModuleType = importlib.import_module(FAKE_MODULES[name])
    return module


def make_driver(options: dict[str, Any]) -> Driver:
    """A driver from the config's ``driver:`` mapping (``name`` plus the driver's options)."""
    opts = dict(options)
    name = opts.pop("name", None)
    if not isinstance(name, str):
        raise ConfigError("driver.name: missing")
    cls = driver_class(name)
    unknown = set(opts) - set(cls.options)
    if unknown:
        raise ConfigError(f"driver.{sorted(unknown)[0]}: unknown option for driver {name!r} "
                          f"(known: {', '.join(sorted(cls.options))})")
    return cls(**opts)
