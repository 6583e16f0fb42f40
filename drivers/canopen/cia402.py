"""CiA 402 (drives and motion control) and CiA 301 facts shared by the CANopen driver and its
fake drives: the power state machine, controlwords, the PDO layout robid uses, error codes.

Nothing here talks to a bus; it is the vocabulary both ends agree on.
"""

from __future__ import annotations

import struct

__all__ = ["CW_SHUTDOWN", "CW_SWITCH_ON", "CW_ENABLE", "CW_QUICK_STOP", "CW_DISABLE_VOLTAGE",
           "CW_FAULT_RESET", "MODE_CSP", "drive_state", "error_words", "RPDO1", "TPDO1",
           "TPDO2", "RPDO1_MAP", "NMT_RESET_COMM", "NMT_START",
           "NMT_PRE_OPERATIONAL", "SYNC_ID", "PROFILE_402", "pdo_entry", "SYNC_OVERFLOW",
           "SYNC_ECHO", "TORQUE_ACTUAL", "sync_counter", "tpdo_maps", "tpdo2_struct"]

# controlwords (CiA 402 §6.2): the low bits of the commands the state machine obeys
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE = 0x000F
CW_QUICK_STOP = 0x0002
CW_DISABLE_VOLTAGE = 0x0000
CW_FAULT_RESET = 0x0080

MODE_CSP = 8  # cyclic synchronous position
PROFILE_402 = 402
SYNC_ID = 0x80
NMT_START, NMT_PRE_OPERATIONAL, NMT_RESET_COMM = 0x01, 0x80, 0x82

# The SYNC carries a counter 1..SYNC_OVERFLOW (CiA 301 §7.2.5, object 0x1019) and every TPDO
# carries the counter of the SYNC at which its values were latched (SYNC_ECHO, a
# manufacturer-specific UNSIGNED8; drives name it differently, hence the driver's sync_echo
# option). A TPDO that comes late (a loaded socketcand host, a busy network) is then still put
# at its own SYNC in the log, and a position and a torque from two different SYNCs are never
# paired: arrival time says nothing about which SYNC a sample answers.
SYNC_OVERFLOW = 240
SYNC_ECHO = (0x2100, 0)


def sync_counter(index: int) -> int:
    """The counter byte of the SYNC with 0-based ``index`` (1..SYNC_OVERFLOW)."""
    return index % SYNC_OVERFLOW + 1


# robid's PDO layout: one RPDO and two TPDOs per drive, all synchronous (transmission type 1);
# the error code 0x603F comes by EMCY (and by SDO after a fault). TPDO2 carries the torque the
# log records: 0x6077 (INTEGER16, per mille of the rated torque: 0.5 N·m steps on a 500 N·m
# joint, near the measurement noise) or a drive's finer object (INTEGER32, e.g. the torque or
# the current actual value in its own unit); the velocity the master needs at standstill comes
# from successive positions, so both fit one frame each with the SYNC echo.
RPDO1 = struct.Struct("<Hih")  # controlword 0x6040, target position 0x607A, torque offset 0x60B2
TPDO1 = struct.Struct("<HiB")  # statusword 0x6041, position actual 0x6064, SYNC echo
TORQUE_ACTUAL = (0x6077, 0)  # INTEGER16, per mille of the rated torque (0x6076)
TPDO2 = struct.Struct("<hB")  # torque actual 0x6077, SYNC echo (a 32-bit object: tpdo2_struct)


def tpdo2_struct(bits: int) -> struct.Struct:
    """TPDO2 (the torque object of ``bits`` bits, SYNC echo)."""
    return struct.Struct({16: "<hB", 32: "<iB"}[bits])


def pdo_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry (CiA 301 §7.5.2.36): index, sub-index, length in bits."""
    return (index << 16) | (subindex << 8) | bits


RPDO1_MAP = (pdo_entry(0x6040, 0, 16), pdo_entry(0x607A, 0, 32), pdo_entry(0x60B2, 0, 16))


def tpdo_maps(echo: tuple[int, int] = SYNC_ECHO, torque: tuple[int, int] = TORQUE_ACTUAL,
              torque_bits: int = 16) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The two TPDO mappings, with the drive's SYNC echo object ``(index, subindex)`` and the
    torque object the log records (``torque_bits`` wide)."""
    return ((pdo_entry(0x6041, 0, 16), pdo_entry(0x6064, 0, 32), pdo_entry(*echo, 8)),
            (pdo_entry(*torque, torque_bits), pdo_entry(*echo, 8)))


# statusword patterns (mask, value, state), CiA 402 table 30
_STATES = ((0x4F, 0x00, "Not ready to switch on"), (0x4F, 0x40, "Switch on disabled"),
           (0x6F, 0x21, "Ready to switch on"), (0x6F, 0x23, "Switched on"),
           (0x6F, 0x27, "Operation enabled"), (0x6F, 0x07, "Quick stop active"),
           (0x4F, 0x0F, "Fault reaction active"), (0x4F, 0x08, "Fault"))


def drive_state(statusword: int) -> str:
    """The power state a statusword reports."""
    for mask, value, name in _STATES:
        if statusword & mask == value:
            return name
    return f"unknown (statusword 0x{statusword:04X})"


# error codes (CiA 301 EMCY classes and CiA 402 annex), the ones drives report most
_ERRORS = {
    0x0000: "no error", 0x1000: "generic error", 0x2211: "internal over-current",
    0x2310: "continuous over-current", 0x2320: "short circuit at the motor output",
    0x3110: "mains over-voltage", 0x3120: "mains under-voltage",
    0x3210: "DC link over-voltage", 0x3220: "DC link under-voltage",
    0x4210: "excess temperature of the device", 0x4310: "excess temperature of the drive",
    0x5113: "supply voltage fault", 0x5441: "STO active (safe torque off)",
    0x6010: "software reset (watchdog)", 0x7121: "motor blocked",
    0x7305: "incremental sensor 1 fault", 0x7500: "communication error",
    0x8110: "CAN overrun (frames lost)", 0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error (master lost)", 0x8140: "recovered from bus-off",
    0x8611: "following error", 0x8612: "reference limit", 0xFF00: "manufacturer-specific",
}
_CLASSES = {0x1: "generic", 0x2: "current", 0x3: "voltage", 0x4: "temperature",
            0x5: "device hardware", 0x6: "device software", 0x7: "additional modules",
            0x8: "monitoring", 0x9: "external error", 0xF: "additional functions"}


def error_words(code: int) -> str:
    """An error code (0x603F, EMCY) in words: ``0x2310 continuous over-current``."""
    words = _ERRORS.get(code) or _ERRORS.get(code & 0xFF00)
    if words is None:
        words = f"{_CLASSES.get(code >> 12, 'unknown')} error"
    return f"0x{code:04X} {words}"
