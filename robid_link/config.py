"""The daemon's config, parsed once into frozen dataclasses whose errors name the key path.

Imports no wing: experiment kinds' options (``kinds.py``) and the file-name rule of experiment
ids (``jobs.py``) are on the door, checked alike by the worker. The YAML reader is ``yamlio.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError, RobidError
from robid_link.jobs import check_name
from robid_link.kinds import KIND_OPTIONS, experiment_options
from robid_link.yamlio import check_keys, read_yaml_mapping, yaml_type

__all__ = ["load_daemon_config", "DaemonConfig", "CampaignDef",
           "ExperimentDef", "WebConfig", "check_store_url", "robot_name", "with_joint_count",
           "SPLIT_KINDS"]


# ----------------------------------------------------------------------------- daemon config

_DAEMON_REQUIRED = ("robot", "state_dir", "control_socket", "driver", "campaigns")
_DAEMON_OPTIONAL = ("lock", "socket_mode", "worker_start_method", "log_level", "web", "store",
                    "robot_name", "log_store")
_WEB_OPTIONAL = ("listen", "tls_cert", "tls_key", "token", "token_file", "hosts")
_CAMPAIGN_OPTIONAL = ("identify", "diagnose", "model", "add", "method", "retries", "backoff_s",
                      "timeout_s", "reduced_speed_first", "cutoff_hz", "motor_side", "upload",
                      "channels", "force")
#: experiment kinds whose logs feed the identification: the ones ``channels`` splits
SPLIT_KINDS = ("rigid_body", "friction", "custom")


@dataclass(frozen=True)
class ExperimentDef:
    """One experiment of a campaign: its id (a file-name-safe word), kind and options."""

    exp_id: str
    kind: str
    options: dict[str, Any]
    #: joints (from 1) whose torque the controller logs; None: every joint's
    torques: tuple[int, ...] | None = None


@dataclass(frozen=True)
class CampaignDef:
    name: str
    experiments: tuple[ExperimentDef, ...]
    identify: bool = True
    diagnose: bool = False
    model: Path | None = None
    add: tuple[str, ...] = ()
    method: str = "ols"
    retries: int = 2
    backoff_s: float = 2.0
    timeout_s: float | None = None  # None: twice the program's duration plus 60 s
    reduced_speed_first: float | None = None
    cutoff_hz: float | None = None
    motor_side: bool = False
    upload: bool = False
    #: the controller's signal budget: torque channels one log may hold (None: every joint's)
    channels: int | None = None
    #: the robot's joint count, once known (``with_joint_count``): ``channels`` splits with it
    n_joints: int | None = None

    def torque_groups(self) -> list[tuple[int, ...]] | None:
        """Joints (from 1) whose torques each split experiment logs: ⌈n / channels⌉ groups of
        consecutive joints (main axes, then wrist axes); None when nothing is split (no
        budget, the robot's joints not known yet, or the budget holds every joint)."""
        n, k = self.n_joints, self.channels
        if n is None or k is None or k >= n:
            return None
        return [tuple(range(a, min(a + k, n + 1))) for a in range(1, n + 1, k)]

    def split_experiments(self) -> tuple[ExperimentDef, ...]:
        """The experiments with ``channels`` applied: each identification experiment
        (``SPLIT_KINDS``) once per torque group, the same motion, ids ``<id>-j1-3``; a friction
        sweep of some joints only in the groups that hold one of them."""
        groups = self.torque_groups()
        if groups is None:
            return self.experiments
        out: list[ExperimentDef] = []
        for e in self.experiments:
            if e.kind not in SPLIT_KINDS:
                out.append(e)
                continue
            swept = e.options.get("joints") if e.kind == "friction" else None
            for g in groups:
                if swept and not set(g) & set(swept):  # sweeps of other joints only
                    continue
                span = f"j{g[0]}" if len(g) == 1 else f"j{g[0]}-{g[-1]}"
                out.append(ExperimentDef(f"{e.exp_id}-{span}", e.kind, e.options, g))
        return tuple(out)
    #: upload a parameter set the worker marked unfit (worse than CAD, physically impossible)
    force: bool = False


@dataclass(frozen=True)
class WebConfig:
    """``web:``: the operator's page. ``listen`` HOST:PORT (the daemon serves it when set);
    TLS certificate and key; the token actions need (given, or in ``token_file``, by default
    ``web.token`` in the state dir, mode 0600); ``hosts``: the names the page is reached by
    besides the listen host and localhost (a request naming another Host is refused)."""

    listen: str | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    token: str | None = None
    token_file: Path | None = None
    hosts: tuple[str, ...] = ()


@dataclass(frozen=True)
class DaemonConfig:
    path: Path
    robot: Path
    state_dir: Path
    control_socket: Path
    driver: dict[str, Any]
    campaigns: dict[str, CampaignDef]
    lock: tuple[str, ...] = ()
    socket_mode: int = 0o660
    worker_start_method: str = "forkserver"
    log_level: str = "info"
    web: WebConfig = WebConfig()
    #: a plant's PostgreSQL store (URL without password); None: SQLite under state_dir
    store: str | None = None
    #: this robot's name in the store; None: the robot description's name
    robot_name: str | None = None
    #: where raw logs go instead of state_dir (a folder or an fsspec URL)
    log_store: str | None = None

    @property
    def base_dir(self) -> Path:
        return self.path.parent


def robot_name(cfg: DaemonConfig, description_name: str | None) -> str:
    """The robot's name in the store, on its page and in its commands: the config's
    ``robot_name``, else the robot description's name (robots of one type share it; a plant's
    store tells them apart by ``robot_name``), else the description file's stem (a
    description that does not load: ``description_name`` None)."""
    return cfg.robot_name or description_name or cfg.robot.stem


#: connection parameters of libpq that are secrets (in a URL's query string as in its user info)
_SECRET_PARAMS = frozenset({"password", "sslpassword"})


def check_store_url(value: Any, key: str = "store") -> str:
    """A PostgreSQL URL with no password in it (the password comes from PGPASSWORD or a
    PGPASSFILE); the one line refusing one never prints it."""
    from urllib.parse import parse_qsl, urlsplit

    if not isinstance(value, str) or not value.startswith(("postgresql://", "postgresql+psycopg://",
                                                           "postgres://")):
        raise ConfigError(f"{key}: expected a PostgreSQL URL like "
                          "postgresql://robid@db.plant:5432/robid")
    try:
        parts = urlsplit(value)
        parts.port  # noqa: B018 - raises on a bad port
    except ValueError:
        raise ConfigError(f"{key}: not a valid URL") from None
    query = {k.lower() for k, _ in parse_qsl(parts.query, keep_blank_values=True)}
    if parts.password is not None or query & _SECRET_PARAMS:
        raise ConfigError(f"{key}: the URL holds a password; give it in PGPASSWORD or a "
                          "PGPASSFILE (~/.pgpass), never in the config or on the command line")
    if not parts.hostname or not parts.path.strip("/"):
        raise ConfigError(f"{key}: expected postgresql://USER@HOST:PORT/DATABASE")
    return value


def _plant_keys(doc: dict[str, Any], base: Path) -> dict[str, Any]:
    """``store``, ``robot_name`` and ``log_store``: a plant's shared store."""
    import re

    out: dict[str, Any] = {}
    if doc.get("store") is not None:
        out["store"] = check_store_url(doc["store"])
    name = doc.get("robot_name")
    if name is not None:
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}",
                                                         name):
            raise ConfigError(f"robot_name: expected 1-64 letters, digits, '_', '.' or '-', "
                              f"got {name!r}")
        out["robot_name"] = name
    logs = doc.get("log_store")
    if logs is not None:
        if not isinstance(logs, str) or not logs:
            raise ConfigError("log_store: expected a folder or an fsspec URL (s3://bucket/robid)")
        out["log_store"] = logs if "://" in logs else str(_path(base, logs, "log_store"))
    return out


def _num(doc: dict[str, Any], key: str, where: str, default: Any, *, positive: bool = True,
         integer: bool = False, high: float = 1e9) -> Any:
    v = doc.get(key, default)
    if v is None:
        return None
    kinds = int if integer else (int, float)
    sign = "a positive" if positive else "a non-negative"
    what = f"{sign} {'integer' if integer else 'number'}"
    if (isinstance(v, bool) or not isinstance(v, kinds)
            or not (isinstance(v, int) or math.isfinite(v)) or (v <= 0 if positive else v < 0)):
        raise ConfigError(f"{where}.{key}: expected {what}, got {v!r}")
    if v > high:  # 10**400 is an int: it would overflow a float later (a sleep, a timeout)
        shown = (str(v) if isinstance(v, int) and v < 10 ** 15
                 else f"an integer of {v.bit_length()} bits" if isinstance(v, int)
                 and v >= 10 ** 300 else f"{v:.3g}")  # a float: 1e305 has no bit_length
        raise ConfigError(f"{where}.{key}: expected {what} up to {high:g}, got {shown}")
    return v


def _path(base: Path, v: Any, where: str) -> Path:
    if not isinstance(v, str) or not v:
        raise ConfigError(f"{where}: expected a path")
    p = Path(v).expanduser()
    return p if p.is_absolute() else base / p


def _experiments(raw: Any, where: str) -> tuple[ExperimentDef, ...]:
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{where}: expected a non-empty list of experiments")
    out: list[ExperimentDef] = []
    for i, entry in enumerate(raw):
        w = f"{where}[{i}]"
        if isinstance(entry, str):
            entry = {"kind": entry}
        if not isinstance(entry, dict):
            raise ConfigError(f"{w}: expected an experiment kind or a mapping with 'kind'")
        opts = dict(entry)
        kind = opts.pop("kind", None)
        if not isinstance(kind, str) or kind not in KIND_OPTIONS:
            raise ConfigError(f"{w}.kind: expected one of {', '.join(KIND_OPTIONS)}, "
                              f"got {kind!r}")
        exp_id = opts.pop("id", kind if i == 0 or all(e.kind != kind for e in out)
                          else f"{kind}-{i + 1}")
        try:
            check_name(str(exp_id), "id")
        except RobidError as err:
            raise ConfigError(f"{w}.id: {err}") from err
        if any(e.exp_id == exp_id for e in out):
            raise ConfigError(f"{w}.id: {exp_id!r} is used twice")
        out.append(ExperimentDef(str(exp_id), kind, experiment_options(kind, opts, w)))
    return tuple(out)


def _upload_step(raw: dict[str, Any], w: str) -> dict[str, Any]:
    """``experiments: [rigid_body, friction, upload, verify]``: the ``upload`` step is the
    campaign's ``upload: true``; a ``verify`` after it runs before the upload too."""
    exps = raw.get("experiments")
    if not isinstance(exps, list) or "upload" not in exps:
        return raw
    if raw.get("upload") is False:
        raise ConfigError(f"{w}.upload: false, but the experiments list an 'upload' step")
    if exps.count("upload") > 1:
        raise ConfigError(f"{w}.experiments: 'upload' listed twice")
    return {**raw, "upload": True, "experiments": [e for e in exps if e != "upload"]}


def _campaign(name: str, raw: Any, base: Path) -> CampaignDef:
    w = f"campaigns.{name}"
    check_keys(raw, w, required=("experiments",), optional=_CAMPAIGN_OPTIONAL)
    raw = _upload_step(raw, w)
    method = raw.get("method", "ols")
    if method not in ("ols", "wls", "irls", "consistent"):
        raise ConfigError(f"{w}.method: expected ols, wls, irls or consistent, got {method!r}")
    add = raw.get("add") or []
    if not isinstance(add, list) or not all(isinstance(a, str) for a in add):
        raise ConfigError(f"{w}.add: expected a list of EFFECT[@J]")
    rsf = _num(raw, "reduced_speed_first", w, None)
    if rsf is not None and rsf >= 1:
        raise ConfigError(f"{w}.reduced_speed_first: expected a fraction in (0, 1), got {rsf!r}")
    for key in ("identify", "diagnose", "motor_side", "upload", "force"):
        if not isinstance(raw.get(key, False), bool):
            raise ConfigError(f"{w}.{key}: expected true or false")
    if raw.get("upload", False) and not raw.get("identify", True):
        raise ConfigError(f"{w}.upload: needs identify: true (nothing to upload otherwise)")
    channels = _num(raw, "channels", w, None, integer=True)
    if channels is not None and not 1 <= channels <= 64:
        raise ConfigError(f"{w}.channels: expected the torque channels one log may hold, "
                          f"1..64, got {channels!r}")
    if channels is not None and raw.get("diagnose", False):
        raise ConfigError(f"{w}.channels: the diagnosis needs every joint's torque in each "
                          "log; set diagnose: false or drop channels")
    experiments = _experiments(raw["experiments"], f"{w}.experiments")
    if channels is not None:
        _check_split_ids(experiments, f"{w}.experiments")
    return CampaignDef(
        name=name, experiments=experiments,
        identify=raw.get("identify", True), diagnose=raw.get("diagnose", False),
        model=_path(base, raw["model"], f"{w}.model") if raw.get("model") else None,
        add=tuple(add), method=method,
        retries=_num(raw, "retries", w, 2, positive=False, integer=True, high=1000),
        backoff_s=_num(raw, "backoff_s", w, 2.0, positive=False),
        timeout_s=_num(raw, "timeout_s", w, None), reduced_speed_first=rsf,
        cutoff_hz=_num(raw, "cutoff_hz", w, None), motor_side=raw.get("motor_side", False),
        upload=raw.get("upload", False), channels=channels,
        force=raw.get("force", False))


def _check_split_ids(experiments: tuple[ExperimentDef, ...], where: str) -> None:
    """Split ids (``<id>-j1-3``) stay names and collide with no other experiment's id."""
    ids = {e.exp_id for e in experiments}
    for i, e in enumerate(experiments):
        if e.kind not in SPLIT_KINDS:
            continue
        longest = f"{e.exp_id}-j64-64"
        try:
            check_name(longest, "id")
        except RobidError as err:
            raise ConfigError(f"{where}[{i}].id: split by channels as {longest!r}: {err}"
                              ) from err
        clash = next((o for o in ids if o.startswith(f"{e.exp_id}-j") and o != e.exp_id), None)
        if clash is not None:
            raise ConfigError(f"{where}[{i}].id: {e.exp_id!r} split by channels would "
                              f"collide with experiment {clash!r}")


def with_joint_count(cfg: DaemonConfig, n_joints: int) -> DaemonConfig:
    """The config with the robot's joint count in every campaign (``channels`` splits)."""
    return replace(cfg, campaigns={k: replace(c, n_joints=n_joints)
                                   for k, c in cfg.campaigns.items()})


def _web(raw: Any, base: Path) -> WebConfig:
    if raw is None:
        return WebConfig()
    check_keys(raw, "web", optional=_WEB_OPTIONAL)
    for key in ("listen", "token"):
        if raw.get(key) is not None and (not isinstance(raw[key], str) or not raw[key]):
            raise ConfigError(f"web.{key}: expected text, got {raw[key]!r}")
    if raw.get("token") is not None and len(raw["token"]) < 16:
        raise ConfigError("web.token: at least 16 characters (a guessable token guards "
                          "nothing)")
    if raw.get("token") and raw.get("token_file"):
        raise ConfigError("web: give token or token_file, not both")
    paths = {k: _path(base, raw[k], f"web.{k}") if raw.get(k) else None
             for k in ("tls_cert", "tls_key", "token_file")}
    return WebConfig(listen=raw.get("listen"), token=raw.get("token"),
                     hosts=_web_hosts(raw.get("hosts", [])), **paths)


def _web_hosts(raw: Any) -> tuple[str, ...]:
    """``web.hosts``: host names or addresses, without a scheme or a port."""
    import ipaddress
    import re

    if not isinstance(raw, list):
        raise ConfigError(f"web.hosts: expected a list of host names, got {raw!r}")
    for k, name in enumerate(raw):
        try:
            ok = isinstance(name, str) and (re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9.-]*", name)
                                            is not None or bool(ipaddress.ip_address(name)))
        except ValueError:
            ok = False
        if not ok:
            raise ConfigError(f"web.hosts[{k}]: expected a host name or address (no scheme "
                              f"or port), got {name!r}")
    return tuple(name.lower().rstrip(".") for name in raw)


def load_daemon_config(path: str | Path) -> DaemonConfig:
    """Read and validate the daemon's config; every error names the file and key path."""
    p = Path(path)
    doc = read_yaml_mapping(p, "daemon config")
    try:
        return _daemon_config(p, doc)
    except ConfigError as err:
        raise ConfigError(f"{p}: {err}") from err


def _daemon_config(p: Path, doc: dict[str, Any]) -> DaemonConfig:
    import re

    check_keys(doc, "", required=_DAEMON_REQUIRED, optional=_DAEMON_OPTIONAL)
    base = p.parent
    driver = doc["driver"]
    if not isinstance(driver, dict):
        raise ConfigError(f"driver: expected a mapping, got {yaml_type(driver)} "
                          "(e.g. driver: {name: file_share, share: DIR})")
    if not isinstance(driver.get("name"), str):
        raise ConfigError("driver: missing key 'name' (e.g. driver: {name: file_share, "
                          "share: DIR})")
    driver = dict(driver)
    if isinstance(driver.get("share"), str):
        driver["share"] = str(_path(base, driver["share"], "driver.share"))
    camps = doc["campaigns"]
    if not isinstance(camps, dict) or not camps:
        raise ConfigError(f"campaigns: expected a mapping of campaign names, got "
                          f"{yaml_type(camps) if camps else 'nothing'}")
    for name in camps:
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_\-]+", name):
            raise ConfigError(f"campaigns.{name}: names are letters, digits, '_' and '-'")
    mode = doc.get("socket_mode", 0o660)
    if isinstance(mode, str):
        try:
            mode = int(mode, 8)
        except ValueError as err:
            raise ConfigError(f"socket_mode: expected octal like '0660', got {mode!r}") from err
    if isinstance(mode, bool) or not isinstance(mode, int) or not 0 <= mode <= 0o777:
        raise ConfigError(f"socket_mode: expected octal like '0660', got {mode!r}")
    start = doc.get("worker_start_method", "forkserver")
    if start not in ("forkserver", "spawn"):
        raise ConfigError(f"worker_start_method: expected forkserver or spawn, got {start!r}")
    level = doc.get("log_level", "info")
    if level not in ("debug", "info", "warning", "error"):
        raise ConfigError(f"log_level: expected debug, info, warning or error, got {level!r}")
    lock = doc.get("lock") or []
    if not isinstance(lock, list) or not all(isinstance(x, str) for x in lock):
        raise ConfigError("lock: expected a list of URDF joint names")
    return DaemonConfig(
        path=p.resolve(), robot=_path(base, doc["robot"], "robot"),
        state_dir=_path(base, doc["state_dir"], "state_dir"),
        control_socket=_path(base, doc["control_socket"], "control_socket"),
        driver=driver, campaigns={n: _campaign(n, c, base) for n, c in camps.items()},
        lock=tuple(lock), socket_mode=mode, worker_start_method=start, log_level=level,
        web=_web(doc.get("web"), base),
        **_plant_keys(doc, base))
