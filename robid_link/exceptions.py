"""One error tree for robid_link, and the warning categories users can filter.

    RobidError
     ├── ConfigError (ValueError)       bad YAML, unknown key, bad value; names the key path
     │    └── UnsafeProgramError        a motion program breaks the robot's limits
     ├── RobotError (ValueError)        robot description cannot be turned into a model
     ├── DataError (ValueError)         a log file is missing, malformed or inconsistent
     ├── ModelError (ValueError)        unknown effect, bad effect option
     ├── EstimationError (ArithmeticError)  too few samples, rank deficiency
     ├── DriverError                    the controller link failed
     │    ├── DriverTimeoutError (TimeoutError)
     │    └── ProtocolError              a malformed answer: the motion may have run, no retry
     ├── CycleError                     an experiment failed after its retries
     ├── ApprovalError                  an unattended run met a program nobody approved
     ├── StoreLockedError (RuntimeError)  the state dir is in use by another daemon
     ├── StoreFullError (OSError)       the state_dir has no room: new runs wait, none fails
     ├── StoreUnavailableError (ConnectionError)  the store's database cannot be reached: the
     │    │                             robot is withdrawn, runs wait, none fails
     │    └── StoreLockLostError        the robot's lock in a shared store was lost: no motion
     ├── DaemonUnreachable (ConnectionError)  no daemon answers on the control socket
     ├── WorkerError (RuntimeError)     a worker process crashed or died (a bug, not bad input)
     └── RecordError (ValueError)       a job or result record of another version, type or keys

    RobidWarning (UserWarning)
     ├── ConditioningWarning            poorly excited / ill-conditioned regressor
     ├── ExcitationWarning              validation outside the training range, weak joints
     └── DataWarning                    saturation, sign/scale mismatch, resampling, gaps
"""

from __future__ import annotations

__all__ = [
    "RobidError",
    "ConfigError",
    "RobotError",
    "DataError",
    "ModelError",
    "EstimationError",
    "DriverError",
    "DriverTimeoutError",
    "ProtocolError",
    "UnsafeProgramError",
    "ApprovalError",
    "CycleError",
    "StoreLockedError",
    "StoreFullError",
    "StoreUnavailableError",
    "StoreLockLostError",
    "DaemonUnreachable",
    "WorkerError",
    "RecordError",
    "RobidWarning",
    "ConditioningWarning",
    "ExcitationWarning",
    "DataWarning",
]


class RobidError(Exception):
    """Base of every error robid_link raises on purpose."""


class ConfigError(RobidError, ValueError):
    """A configuration file or option is invalid; the message names the key path."""


class UnsafeProgramError(ConfigError):
    """A motion program breaks the robot's limits; it never reaches the controller."""


class ApprovalError(RobidError):
    """An unattended (timer-started) run met a program no operator approved."""


class RobotError(RobidError, ValueError):
    """A robot description (MDH YAML or URDF) cannot be turned into a model."""


class DataError(RobidError, ValueError):
    """A log file is missing, malformed or inconsistent with the robot."""


class ModelError(RobidError, ValueError):
    """A model file or effect entry is invalid."""


class EstimationError(RobidError, ArithmeticError):
    """The estimation problem cannot be solved as posed."""


class DriverError(RobidError):
    """The controller link failed."""


class DriverTimeoutError(DriverError, TimeoutError):
    """The controller did not answer in time."""


class ProtocolError(DriverError):
    """The controller answered, but malformed: it may have moved, so no automatic retry."""


class CycleError(RobidError):
    """An experiment failed after its retries (the last attempt's error is its cause)."""


class StoreLockedError(RobidError, RuntimeError):
    """The state dir is locked by another running daemon."""


class DaemonUnreachable(RobidError, ConnectionError):
    """No daemon answers on the control socket."""


class WorkerError(RobidError, RuntimeError):
    """A worker process crashed (an unexpected exception) or died without an answer."""


class RecordError(RobidError, ValueError):
    """A job or result record that this side cannot read: another schema version, an unknown
    record type, a missing or unknown key (the message names the record and key)."""


class RobidWarning(UserWarning):
    """Base of robid_link's warnings."""


class ConditioningWarning(RobidWarning):
    """The regressor is ill-conditioned; some parameters are poorly determined."""


class ExcitationWarning(RobidWarning):
    """Validation data leaves the training range, or a joint is weakly excited."""


class DataWarning(RobidWarning):
    """A log looks suspicious: saturation, gaps, resampling, sign or scale mismatch."""


class StoreFullError(RobidError, OSError):
    """The state_dir's disk is full (or below its reserve): the daemon refuses new runs and
    pauses the current one before its next motion; it resumes when space returns."""


class StoreUnavailableError(RobidError, ConnectionError):
    """The store's database cannot be reached (a PostgreSQL server down, a connection lost):
    like a full disk, the daemon withdraws what it gave, pauses the run and serves status; it
    resumes when the store answers again. The message names the store (no password)."""


class StoreLockLostError(StoreUnavailableError):
    """A daemon's lock on its robot in a shared store was lost (its session ended and another
    daemon may hold the robot now): latched, no further motion until the daemon restarts."""
