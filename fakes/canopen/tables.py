"""CANopen facts the fake drives need, written from the CiA documents (CiA 301 v4.2
"CANopen application layer and communication profile"; CiA 402-2 v4.1 / IEC 61800-7-201
"Drives and motion control device profile"), each with the section it comes from. Nothing here
comes from the daemon's driver.
"""

from __future__ import annotations

__all__ = ["COB_NMT", "COB_SYNC", "COB_EMCY", "COB_TPDO1", "COB_RPDO1", "COB_TPDO2",
           "COB_SDO_TX", "COB_SDO_RX", "COB_HEARTBEAT", "NMT_START", "NMT_STOP",
           "NMT_PRE_OPERATIONAL", "NMT_RESET_NODE", "NMT_RESET_COMMUNICATION", "MODE_CSP",
           "QUICK_STOP_TO_DISABLED", "STATUSWORD", "EMCY_OVER_CURRENT", "EMCY_HEARTBEAT",
           "ERROR_REGISTER_GENERIC", "ERROR_REGISTER_COMMUNICATION", "SYNC_ECHO", "next_state",
           "error_text"]

# CiA 301 §7.3.3, the pre-defined connection set ("broadcast objects", "peer-to-peer
# objects"): a function code in bits 10-7 of the 11-bit COB-ID, plus the
# node id (1-127) for the peer-to-peer objects
COB_NMT = 0x000
COB_SYNC = 0x080
COB_EMCY = 0x080       # + node id
COB_TPDO1 = 0x180      # + node id
COB_RPDO1 = 0x200      # + node id
COB_TPDO2 = 0x280      # + node id
COB_SDO_TX = 0x580     # + node id: server → client
COB_SDO_RX = 0x600     # + node id: client → server
COB_HEARTBEAT = 0x700  # + node id: NMT error control (boot-up, heartbeat)

# CiA 301 §7.2.8.3.1.1, NMT module control: byte 0 the command specifier, byte 1 the node id
# (0: all nodes)
NMT_START = 0x01
NMT_STOP = 0x02
NMT_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

# CiA 402-2, object 6060h "Modes of operation": 8 = cyclic synchronous position mode
MODE_CSP = 8
# CiA 402-2 object 605Ah "Quick stop option code": 2 = slow down on the quick stop ramp, then
# Switch on disabled
QUICK_STOP_TO_DISABLED = 2

# CiA 402-2, object 6041h "Statusword", table "State coding": bits 0-3, 5 and 6 code the
# power state (bit 5 "quick stop" is 0 while a quick stop is active); bit 4 "voltage enabled"
# is set where the power stage has voltage, bit 9 "remote" always (the drive obeys the
# controlword)
STATUSWORD = {"Not ready to switch on": 0x0200, "Switch on disabled": 0x0240,
              "Ready to switch on": 0x0231, "Switched on": 0x0233,
              "Operation enabled": 0x0237, "Quick stop active": 0x0217,
              "Fault reaction active": 0x021F, "Fault": 0x0208}


def next_state(state: str, controlword: int, previous: int) -> str:
    """The power state after a controlword (CiA 402-2, figure "Finite state automaton" and
    table "Command coding"; the numbers are the transitions there). Commands (bits 7, 3-0):
    Shutdown 0xxx x110, Switch on 0xxx 0111, Enable operation 0xxx 1111,
    Disable voltage 0xxx xx0x, Quick stop 0xxx x01x, Disable operation 0xxx 0111,
    Fault reset: bit 7 rising."""
    cw = controlword
    if state == "Fault":
        return "Switch on disabled" if cw & 0x80 and not previous & 0x80 else state  # 15
    if state in ("Not ready to switch on", "Fault reaction active"):
        return state  # left by the drive itself, not by a command
    if cw & 0x80:
        return state  # fault reset outside Fault: no transition
    disable_voltage = cw & 0x02 == 0
    quick_stop = cw & 0x06 == 0x02
    shutdown = cw & 0x07 == 0x06
    switch_on = cw & 0x0F == 0x07
    enable = cw & 0x0F == 0x0F
    if state == "Switch on disabled":
        return "Ready to switch on" if shutdown else state  # 2
    if state == "Ready to switch on":
        if switch_on:
            return "Switched on"  # 3
        if enable:
            return "Operation enabled"  # 3 + 4
        return "Switch on disabled" if disable_voltage or quick_stop else state  # 7
    if state == "Switched on":
        if enable:
            return "Operation enabled"  # 4
        if shutdown:
            return "Ready to switch on"  # 6
        return "Switch on disabled" if disable_voltage or quick_stop else state  # 10
    if state == "Operation enabled":
        if switch_on:
            return "Switched on"  # 5 (disable operation)
        if shutdown:
            return "Ready to switch on"  # 8
        if quick_stop:
            return "Quick stop active"  # 11
        return "Switch on disabled" if disable_voltage else state  # 9
    if state == "Quick stop active":
        return "Switch on disabled" if disable_voltage else state  # 12
    return state


# CiA 301 §7.2.7.3.1, EMCY write: bytes 0-1 the emergency error code, byte 2 the error
# register (object 1001h; bit 0 generic error), bytes 3-7 manufacturer-specific
ERROR_REGISTER_GENERIC = 0x01
ERROR_REGISTER_COMMUNICATION = 0x10
# CiA 402-2 annex (error codes of drives) and CiA 301 table 21 ("Emergency error codes")
EMCY_OVER_CURRENT = 0x2310   # continuous over-current
EMCY_HEARTBEAT = 0x8130      # life guard error or heartbeat error
_ERROR_TEXT = {0x0000: "no error", EMCY_OVER_CURRENT: "continuous over-current",
               EMCY_HEARTBEAT: "life guard or heartbeat error (master lost)"}

# robid's convention (README, "CiA 402 drives"): each TPDO carries the counter of the SYNC its
# values were latched at (CiA 301 §7.2.5: the SYNC's 1-byte counter when 1019h > 1) in a
# manufacturer-specific UNSIGNED8; the fake drives' EDS has it at 2100h:00
SYNC_ECHO = (0x2100, 0)


def error_text(code: int) -> str:
    return f"0x{code:04X} {_ERROR_TEXT.get(code, 'error')}"
