"""Driver lookup: a built-in table of ``name → module:Class`` extended by the entry-point group
``robid_link.drivers``. A driver module is imported only when it is chosen."""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from robid_link.exceptions import ConfigError
from robid_link.link.driver import Driver

__all__ = ["BUILTIN_DRIVERS", "available_drivers", "driver_class", "make_driver"]

ENTRY_POINT_GROUP = "robid_link.drivers"

#: drivers shipped with robid_link; later issues add tcp_rpc, canopen_drives, modbus_plc,
#: serial_line. The value names the extra that installs the driver's library, if any.
BUILTIN_DRIVERS: dict[str, tuple[str, str | None]] = {
    "file_share": ("robid_link.drivers.file_share:FileShareDriver", None),
}


def available_drivers() -> dict[str, str]:
    """Every driver name → ``module:Class``: built-ins, then installed plug-ins."""
    table = {name: target for name, (target, _) in BUILTIN_DRIVERS.items()}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        table.setdefault(ep.name, ep.value)
    return table


def driver_class(name: str) -> type[Driver]:
    table = available_drivers()
    if name not in table:
        raise ConfigError(f"driver.name: unknown driver {name!r} "
                          f"(available: {', '.join(sorted(table))})")
    module_name, _, attr = table[name].partition(":")
    extra = BUILTIN_DRIVERS.get(name, ("", None))[1]
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        hint = f"; install it with: pip install 'robid_link[{extra}]'" if extra else ""
        raise ConfigError(f"driver.name: driver {name!r} cannot be imported "
                          f"({err.name or err}){hint}") from err
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise ConfigError(f"driver.name: {table[name]} is not a robid_link Driver")
    return cls


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
