"""Campaign runs: every experiment's program generated and checked up front (unattended runs
only with operator-approved programs), then the cycles in order, then identification (and
diagnosis) in a worker process; results into the store. Runs resume from the journal."""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from robid_link import jobs as jb
from robid_link.config import (
    CampaignDef,
    DaemonConfig,
    ExperimentDef,
    robot_name,
    with_joint_count,
)
from robid_link.exceptions import (
    ApprovalError,
    ConfigError,
    RobidError,
    StoreFullError,
    StoreUnavailableError,
)
from robid_link.jobs import MotionProgram
from robid_link.link.checks import ModelWatch, campaign_findings
from robid_link.link.cycle import CyclePolicy, MotionWithheld, Withdrawn, run_cycle
from robid_link.link.driver import CAP_UPLOAD, Driver, FeedforwardSource, parameter_bytes
from robid_link.link.store import AsyncStore, Store
from robid_link.link.worker import run_here, run_in_worker

__all__ = ["TRIGGERS", "UNATTENDED", "plan", "check_approved", "check_capabilities", "create_run",
           "prepare_programs", "preflight", "check_config", "describe_campaigns", "execute_run",
           "resonance_hints", "feedforward_source", "drift_flags", "drift_flags_of"]

log = logging.getLogger("robid.campaign")

#: starts nobody is known to watch from beside the robot (a timer; the web page, which may be
#: far from the cell): they move only programs an operator approved by hash (``robid campaign
#: approve``) and upload only approved parameter sets, resumed after a restart too
UNATTENDED = ("timer", "web")
TRIGGERS = ("operator", *UNATTENDED)
BEFORE_SUFFIX = "-before"
SLOW_SUFFIX = "-slow"


def plan(camp: CampaignDef) -> list[tuple[str, ExperimentDef, float | None]]:
    """The run's experiments in order: ``(exp_id, definition, reduced speed or None)``. With
    an upload, each ``verify`` runs first as ``<id>-before`` (the controller's old model) and
    again after the upload under its own id."""
    out: list[tuple[str, ExperimentDef, float | None]] = []
    experiments = camp.split_experiments()  # the channels budget, once the robot is known
    before = [e for e in experiments if camp.upload and e.kind == "verify"]
    for exp_id, exp in [(e.exp_id + BEFORE_SUFFIX, e) for e in before] + [
            (e.exp_id, e) for e in experiments]:
        if camp.reduced_speed_first:
            out.append((exp_id + SLOW_SUFFIX, exp, camp.reduced_speed_first))
        out.append((exp_id, exp, None))
    return out


def after_upload(camp: CampaignDef, exp_id: str) -> bool:
    """A verify experiment run after the upload (the rest run before identification)."""
    return camp.upload and any(e.kind == "verify" and exp_id in (e.exp_id,
                                                                 e.exp_id + SLOW_SUFFIX)
                               for e in camp.experiments)


def check_capabilities(cfg: DaemonConfig, driver: Driver) -> None:
    """Refuse, before anything moves, a campaign that needs what the driver cannot do (an
    upload of the identified parameters needs ``CAP_UPLOAD``)."""
    for name in cfg.campaigns:
        refusal = _capability_refusal(cfg, name, driver)
        if refusal:
            raise ConfigError(f"{cfg.path}: {refusal}")


def _capability_refusal(cfg: DaemonConfig, name: str, driver: Driver) -> str | None:
    """Why campaign ``name`` needs what the driver cannot do, or None (the daemon's start and
    ``robid config check`` say it in the same words)."""
    caps = frozenset(driver.capabilities)
    if cfg.campaigns[name].upload and CAP_UPLOAD not in caps:
        return (f"campaigns.{name}.upload: driver {driver.name!r} cannot upload parameters "
                f"(capabilities: {', '.join(sorted(caps)) or 'none'}); set upload: false or "
                "use a driver that can")
    return None


def _model_job(cfg: DaemonConfig, name: str) -> jb.ModelCheckJob:
    """The campaign's model check; first its files (model, custom trajectories) are there."""
    camp = cfg.campaigns[name]
    files = campaign_findings(cfg, name)
    if files:
        raise ConfigError(files[0].line)
    return jb.ModelCheckJob(str(camp.model) if camp.model else None, camp.add)


def _program_job(cfg: DaemonConfig, exp_id: str, exp: ExperimentDef, slow: float | None
                 ) -> jb.ProgramJob:
    return jb.ProgramJob(str(cfg.robot), cfg.lock, exp_id, exp.kind, exp.options,
                         str(cfg.base_dir), slow, exp.torques)


async def preflight(cfg: DaemonConfig, store: AsyncStore, ctx: Any, campaign: str,
                    trigger: str = "operator") -> None:
    """Everything a run of ``campaign`` will need, checked before any program is given: the
    model file and ``add:`` effects load, every program generates and passes the limits; an
    unattended start (timer, web page) is refused here unless every program is approved."""
    await run_in_worker(ctx, _model_job(cfg, campaign))
    programs = await prepare_programs(cfg, store, ctx, campaign)
    if trigger in UNATTENDED:
        await check_approved(cfg, store, campaign, programs, trigger)


async def check_approved(cfg: DaemonConfig, store: AsyncStore, campaign: str,
                         programs: list[tuple[str, MotionProgram]], trigger: str) -> None:
    """ApprovalError (one line: which program, how many, how to approve them) unless an
    operator approved every program of an unattended start (``UNATTENDED``): a timer has
    nothing to do, a web start is refused."""
    missing = [(e, p) for e, p in programs if not await store.approved(p.sha256)]
    if missing:
        exp_id, prog = missing[0]
        more = f" ({len(missing)} of {len(programs)} are not)" if len(missing) > 1 else ""
        what = ("web start refused" if trigger == "web" else
                f"campaign {campaign}: nothing to do unattended")
        raise ApprovalError(f"{what}: the program of experiment {exp_id} "
                            f"({prog.sha256[:12]}) is not approved{more}; run: robid campaign "
                            f"approve {campaign} --config {cfg.path}")


def check_config(cfg: DaemonConfig, driver: Driver) -> dict[str, str | None]:
    """``robid config check``: the pre-flight of every campaign without a daemon, in this
    process; campaign name → None (ok) or the reason a run would be refused."""
    verdict: dict[str, str | None] = {}
    cfg = _joints_known(cfg)
    for name in cfg.campaigns:
        try:
            refusal = _capability_refusal(cfg, name, driver)
            if refusal:
                raise ConfigError(refusal)
            run_here(_model_job(cfg, name))
            for exp_id, exp, slow in plan(cfg.campaigns[name]):
                run_here(_program_job(cfg, exp_id, exp, slow))
            verdict[name] = None
        except RobidError as err:
            verdict[name] = str(err)
    return verdict


def _joints_known(cfg: DaemonConfig) -> DaemonConfig:
    """A config read without a daemon, with the robot's joint count where a campaign's
    ``channels`` needs it to split its experiments (the robot read in this process)."""
    if all(c.channels is None or c.n_joints is not None for c in cfg.campaigns.values()):
        return cfg
    info = run_here(jb.RobotInfoJob(str(cfg.robot), cfg.lock))
    assert isinstance(info, jb.RobotInfo)
    return with_joint_count(cfg, info.n)


def describe_campaigns(cfg: DaemonConfig) -> list[dict[str, Any]]:
    """The campaigns as ``campaign list`` shows them (from the config and the robot)."""
    cfg = _joints_known(cfg)
    return [{"name": name,
             "experiments": [{"id": e, "kind": d.kind, "reduced_speed": s}
                             for e, d, s in plan(camp)],
             "identify": camp.identify, "diagnose": camp.diagnose}
            for name, camp in cfg.campaigns.items()]


async def create_run(cfg: DaemonConfig, store: AsyncStore, campaign: str, trigger: str,
                     force: bool = False) -> str:
    """A queued run; ``force``: the operator lets it upload a set the worker marked unfit."""
    if campaign not in cfg.campaigns:
        raise ConfigError(f"campaign {campaign!r}: not in {cfg.path} "
                          f"(known: {', '.join(sorted(cfg.campaigns))})")
    if trigger not in TRIGGERS:
        raise ConfigError(f"trigger: expected {', '.join(TRIGGERS)}, got {trigger!r}")
    camp = cfg.campaigns[campaign]
    exps = [(exp_id, exp.kind) for exp_id, exp, _ in plan(camp)]
    # how the run identifies: what a fleet re-identification repeats with another model
    spec = {"campaign": campaign, "identify": {"method": camp.method,
                                               "cutoff_hz": camp.cutoff_hz,
                                               "motor_side": camp.motor_side},
            **({"force": True} if force else {})}
    return await store.create_run(campaign, trigger, spec, exps)


def _program_key(cfg: DaemonConfig, exp: ExperimentDef, slow: float | None, exp_id: str) -> str:
    """Same robot, definition (and custom file) → same key → same cached, approvable program."""
    h = hashlib.sha256()
    h.update(cfg.robot.read_bytes())
    extra = b""
    if exp.kind == "custom":
        path = Path(exp.options["trajectory"])
        path = path if path.is_absolute() else cfg.base_dir / path
        for p in (path, path.with_suffix(".yaml")):
            try:
                extra += hashlib.sha256(p.read_bytes()).digest()
            except OSError as err:
                raise ConfigError(f"{p}: custom trajectory unreadable ({err.strerror})") from err
    h.update(extra)
    h.update(json.dumps([exp_id, exp.kind, exp.options, slow, list(cfg.lock),
                         None if exp.torques is None else list(exp.torques)],
                        sort_keys=True, default=str).encode())
    return h.hexdigest()


async def prepare_programs(cfg: DaemonConfig, store: AsyncStore, ctx: Any, campaign: str
                           ) -> list[tuple[str, MotionProgram]]:
    """Generate (or take from the cache) and limit-check every program of a campaign."""
    out = []
    for exp_id, exp, slow in plan(cfg.campaigns[campaign]):
        key = _program_key(cfg, exp, slow, exp_id)
        sha = await _generated(cfg, store, ctx, campaign, key, exp_id, exp, slow)
        out.append((exp_id, await store.load_program(sha)))
    return out


# program key (per store) -> the generation under way: a second caller (the start-up pre-flight
# and a 'start' request, two campaigns sharing an experiment) waits for it instead of spending
# the same minutes of CPU again next to it
_generating: dict[tuple[int, str], asyncio.Future[None]] = {}


async def _generated(cfg: DaemonConfig, store: AsyncStore, ctx: Any, campaign: str, key: str,
                     exp_id: str, exp: ExperimentDef, slow: float | None) -> str:
    token = (id(store), key)
    while True:
        sha = await store.program_for(key)
        if sha is not None:
            return sha
        pending = _generating.get(token)
        if pending is None:
            break
        await asyncio.wait([pending])  # it failed or was cancelled: the cache says which
    done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
    _generating[token] = done
    try:
        prog = await run_in_worker(ctx, _program_job(cfg, exp_id, exp, slow))
        sha = await store.put_program(key, prog)
    finally:
        del _generating[token]
        done.set_result(None)
    log.info("campaign=%s exp=%s program=%s generated (%.1f s of motion)", campaign,
             exp_id, sha[:12], prog.duration_s)
    return sha


async def execute_run(cfg: DaemonConfig, store: AsyncStore, driver: Driver, ctx: Any, run_id: str,
                      n_joints: int, kill_hook: Callable[[str], None] = lambda step: None,
                      models: ModelWatch | None = None, *, may_give: bool = True,
                      on_withdrawn: Withdrawn = lambda exp_id, nonce: None) -> None:
    """Run or resume ``run_id`` to completed/failed (logs are checked for ``n_joints``, the
    robot's). Cancellation leaves it resumable, and so does a store that cannot be written
    (full, unreachable: StoreFullError, StoreUnavailableError go on to the daemon, what was
    given withdrawn first). Without ``may_give`` (a daemon's first look at
    a run it found unfinished) only its bookkeeping is done — what was given before is taken
    and stored, what needs no motion is computed — and it stops ``interrupted`` where a program
    or a parameter set would go to the controller. ``models``: a model file edited since it was
    last read is reloaded with a line in the log."""
    run = await store.run(run_id)
    camp = cfg.campaigns.get(run["campaign"])
    if camp is None:
        await store.set_run(run_id, "failed", error=f"campaign {run['campaign']!r} is no "
                            f"longer in {cfg.path}")
        return
    await store.set_run(run_id, "running", step="generating programs" if may_give else
                        "bookkeeping after a restart (no motion)")
    try:
        programs = await _pinned_programs(cfg, store, ctx, run_id, run["campaign"])
        if run["trigger"] in UNATTENDED:
            await check_approved(cfg, store, run["campaign"], programs, run["trigger"])

        # the identification's inputs, before the first motion (a config edited since start)
        model = await run_in_worker(ctx, _model_job(cfg, run["campaign"]))
        changed = models.seen(cfg, run["campaign"], model.effects) if models else None
        if changed:
            log.info("run=%s %s", run_id, changed)

        async def check(path: str) -> jb.LogCheck:
            return await run_in_worker(ctx, jb.LogCheckJob(path, n_joints))

        kinds = {e: d.kind for e, d, _ in plan(camp)}
        first = [(e, p) for e, p in programs if not after_upload(camp, e)]
        then = [(e, p) for e, p in programs if after_upload(camp, e)]
        shas: dict[str, str] = {}

        async def cycle(k: int, exp_id: str, program: MotionProgram) -> None:
            await store.set_run(run_id, "running",
                                step=f"experiment {k}/{len(programs)} {exp_id}")
            policy = CyclePolicy(camp.timeout_s or 2 * program.duration_s + 60.0, camp.retries,
                                 camp.backoff_s)
            shas[exp_id] = await run_cycle(store, driver, run_id, exp_id, program, policy,
                                           check, kill_hook, may_give=may_give,
                                           on_withdrawn=on_withdrawn)

        for k, (exp_id, program) in enumerate(first, 1):
            await cycle(k, exp_id, program)
        if camp.identify:
            data = [s for e, s in shas.items() if kinds.get(e) not in ("verify", "elasticity")]
            await _identify(cfg, store, driver, ctx, run_id, camp, data, n_joints, kill_hook,
                            may_give)
        for k, (exp_id, program) in enumerate(then, len(first) + 1):
            await cycle(k, exp_id, program)
        await _tracking(cfg, store, ctx, run_id, camp, [(e, p, shas[e]) for e, p in programs
                                                        if kinds.get(e) == "verify"])
        await _elasticity(cfg, store, ctx, run_id, camp, [(e, p, shas[e]) for e, p in programs
                                                          if kinds.get(e) == "elasticity"])
    except (StoreFullError, StoreUnavailableError):
        raise  # not the run's fault: it waits, journaled as it is, until the store is back
    except MotionWithheld as held:
        await store.set_run(run_id, "interrupted", step=f"waiting for the operator before "
                            f"{held.exp_id}: robid campaign resume {run_id}")
        log.warning("run=%s interrupted by a restart; bookkeeping done, no motion until an "
                    "operator resumes it (robid campaign resume %s)", run_id, run_id)
        return
    except RobidError as err:
        await store.set_run(run_id, "failed", error=str(err))
        log.error("run=%s failed: %s", run_id, err)
        return
    await store.set_run(run_id, "completed")
    log.info("run=%s completed", run_id)


async def _pinned_programs(cfg: DaemonConfig, store: AsyncStore, ctx: Any, run_id: str,
                           campaign: str) -> list[tuple[str, MotionProgram]]:
    """Programs of the run; an experiment already handed out keeps the program it was given
    (a config edited between a crash and the restart cannot change a half-run experiment)."""
    fresh = dict(await prepare_programs(cfg, store, ctx, campaign))
    out = []
    for row in await store.experiments(run_id):
        if row["program_sha"]:
            out.append((row["exp_id"], await store.load_program(row["program_sha"])))
        elif row["exp_id"] in fresh:
            out.append((row["exp_id"], fresh[row["exp_id"]]))
        else:
            raise ConfigError(f"run {run_id}: experiment {row['exp_id']} is no longer in "
                              f"campaign {campaign}")
    return out


def elasticity_entries(cfg: DaemonConfig) -> dict[int, str]:
    """Joint → the first campaign experiment that measures its elasticity. Without joints or
    pairs an experiment measures every joint (listed up to 64: hints ask only for the
    robot's)."""
    out: dict[int, str] = {}
    for camp in cfg.campaigns.values():
        for exp in camp.experiments:
            if exp.kind != "elasticity":
                continue
            joints = exp.options.get("joints")
            pairs = exp.options.get("pairs") or []
            covered = ([*(joints or ()), *(j for p in pairs for j in p)]
                       if joints or pairs else list(range(1, 65)))
            for j in covered:
                out.setdefault(int(j), f"campaign '{camp.name}' (experiment '{exp.exp_id}', "
                                       f"robid campaign start {camp.name})")
    return out


def resonance_hints(cfg: DaemonConfig, campaign: str, n_joints: int
                    ) -> tuple[jb.ResonanceHint, ...]:
    """Per joint, what the diagnosis says of an unexplained resonance in a run of
    ``campaign``: the campaign experiment that measures the joint's elasticity, else the
    entry to add to ``campaign`` (the config's language stays on the link's side)."""
    entries = elasticity_entries(cfg)
    out = []
    for j in range(1, n_joints + 1):
        entry = entries.get(j)
        todo = (f"measured by {entry}" if entry is not None else
                f"add an elasticity experiment for joint {j}: campaigns.{campaign}.experiments: "
                f"[…, {{kind: elasticity, joints: [{j}]}}] (or robid excite --kind elasticity "
                f"--joint {j})")
        out.append(jb.ResonanceHint(j, entry, todo))
    return tuple(out)


async def _identify(cfg: DaemonConfig, store: AsyncStore, driver: Driver, ctx: Any, run_id: str,
                    camp: CampaignDef, shas: list[str], n_joints: int,
                    kill_hook: Callable[[str], None], may_give: bool = True) -> None:
    """Identify (once per run: a run identified before a restart keeps its result and
    parameter set), then upload the set if the campaign says so — a controller command,
    withheld like motion until an operator resumes an interrupted run."""
    robot, sha = await _identified(store, run_id)
    if sha is None:
        robot, sha = await _identify_now(cfg, store, ctx, run_id, camp, shas, n_joints,
                                         kill_hook)
    if not camp.upload or any(u["run_id"] == run_id and u["state"] == "acknowledged"
                              for u in await store.uploads(robot)):
        return
    if not may_give:
        raise MotionWithheld("upload")
    run = await store.run(run_id)
    await upload_set(store, driver, robot, sha, run_id, unattended=run["trigger"] in UNATTENDED,
                     force=camp.force or run["spec"].get("force") is True)


async def _identified(store: AsyncStore, run_id: str) -> tuple[str, str | None]:
    """The robot and parameter set of the run's identification, if it ended before."""
    for res in await store.results(run_id=run_id):
        if res["kind"] == "identify":
            sets = [s for s in await store.param_sets(res["robot"]) if s["run_id"] == run_id]
            return res["robot"], (sets[-1]["sha256"] if sets else None)
    return "", None


async def _identify_now(cfg: DaemonConfig, store: AsyncStore, ctx: Any, run_id: str,
                        camp: CampaignDef, shas: list[str], n_joints: int,
                        kill_hook: Callable[[str], None]) -> tuple[str, str]:
    await store.set_run(run_id, "running", step="identifying" + (" and diagnosing"
                                                                 if camp.diagnose else ""))
    job = jb.IdentifyJob(
        run_id=run_id, robot=str(cfg.robot), lock=cfg.lock,
        logs=tuple([str(await store.check_log(s)) for s in shas]),
        report_dir=str(store.dir / "reports" / run_id),
        model=str(camp.model) if camp.model else None, add=camp.add, method=camp.method,
        diagnose=camp.diagnose, cutoff_hz=camp.cutoff_hz, motor_side=camp.motor_side,
        upload=camp.upload, resonance_hints=resonance_hints(cfg, camp.name, n_joints),
        campaign=camp.name)
    kill_hook("identifying")
    out: jb.IdentifyOutcome = await run_in_worker(
        ctx, job, on_start=lambda: kill_hook("identify_started"))
    robot = robot_name(cfg, out.robot)
    for kind, rec in out.records.items():
        await store.add_result(run_id, robot, kind, rec)
    log.info("run=%s identified: rmse %s", run_id,
             " ".join(f"{x:.3g}" for x in out.records["identify"]["rmse"] or []))
    for flag in drift_flags_of(await store.results(robot), robot, run_id):
        await store.note(run_id, None, "drift", parameter=flag.parameter, kind=flag.kind,
                         change=round(flag.change, 4), sigmas=round(flag.sigmas, 1))
        log.warning("run=%s drift: %s", run_id, flag.message)
    pset = dict(out.parameter_set.doc)
    body = parameter_bytes(pset)
    version = await store.add_param_set(pset, body)
    log.info("run=%s parameter set %d of %s: %s", run_id, version, robot,
             pset["sha256"][:12])
    return robot, str(pset["sha256"])


async def _tracking(cfg: DaemonConfig, store: AsyncStore, ctx: Any, run_id: str,
                    camp: CampaignDef, runs: list[tuple[str, MotionProgram, str]]) -> None:
    """How the robot followed each verification path (before / after the upload)."""
    if not runs:
        return

    def phase(exp_id: str) -> str:
        if exp_id.removesuffix(SLOW_SUFFIX).endswith(BEFORE_SUFFIX):
            return "before"
        return "after" if camp.upload else "check"

    job = jb.VerifyJob(str(cfg.robot), cfg.lock, tuple([
        jb.VerifyRun(e, phase(e), str(await store.check_log(sha)), p) for e, p, sha in runs]),
        report_dir=str(store.dir / "reports" / run_id), run_id=run_id, campaign=camp.name)
    out: jb.VerifyOutcome = await run_in_worker(ctx, job)
    for rec in map(dict, out.records):
        rec["run_id"] = run_id
        await store.add_result(run_id, robot_name(cfg, out.robot), f"verify_{rec['phase']}",
                               rec)
        log.info("run=%s %s: tool RMS %.3f mm, max %.3f mm", run_id, rec["experiment"],
                 rec["tracking"]["tool_rms_mm"], rec["tracking"]["tool_max_mm"])


def drift_flags(store: Store, robot: str, run_id: str | None = None) -> list[jb.DriftFlag]:
    """Drift flags of ``robot``'s stored identifications (of one run, or all), read from a
    blocking store (the operator commands' reader)."""
    return drift_flags_of(store.results(robot), robot, run_id)


def drift_flags_of(results: list[dict[str, Any]], robot: str, run_id: str | None = None
                   ) -> list[jb.DriftFlag]:
    """Drift flags of ``robot`` in its stored ``results`` (of one run, or all): a DriftJob run
    here (pure Python, quick: the status answers with it)."""
    report = run_here(jb.DriftJob(robot, tuple(results), run_id))
    assert isinstance(report, jb.DriftReport)
    return list(report.flags)


def feedforward_source(cfg: DaemonConfig, ctx: Any) -> FeedforwardSource:
    """What a ``CAP_FEEDFORWARD`` driver calls for the torques of its setpoints: a
    FeedforwardJob on the daemon's robot in a worker process."""

    async def source(pset: jb.ParameterSet, period_s: float, q: Any) -> jb.FeedforwardTable:
        job = jb.FeedforwardJob(str(cfg.robot), cfg.lock, pset, float(period_s),
                                tuple(tuple(float(x) for x in row) for row in q))
        table: jb.FeedforwardTable = await run_in_worker(ctx, job)
        return table

    return source


async def _elasticity(cfg: DaemonConfig, store: AsyncStore, ctx: Any, run_id: str,
                      camp: CampaignDef, runs: list[tuple[str, MotionProgram, str]]) -> None:
    """Two-mass fits of each elasticity experiment (its schedule from the program header)."""
    if not runs:
        return
    await store.set_run(run_id, "running", step="elasticity")
    job = jb.ElasticityJob(str(cfg.robot), cfg.lock, tuple([
        jb.ElasticityRun(e, str(await store.check_log(sha)), p) for e, p, sha in runs]),
        report_dir=str(store.dir / "reports" / run_id), run_id=run_id, campaign=camp.name)
    out: jb.ElasticityOutcome = await run_in_worker(ctx, job)
    rec = {"kind": "elasticity", "run_id": run_id, "robot": out.robot,
           "experiments": [dict(r) for r in out.results]}
    await store.add_result(run_id, robot_name(cfg, out.robot), "elasticity", rec)
    for res in out.results:
        for j in res["result"].get("joints", []):
            log.info("run=%s %s joint %d: K %.4g, D %.4g, f_res %.3g Hz", run_id,
                     res["experiment"], j["joint"], j["k"], j["d"], j["f_res_hz"])


async def upload_set(store: AsyncStore, driver: Driver, robot: str, sha: str, run_id: str | None,
                     *, unattended: bool, force: bool = False, timeout_s: float = 120.0) -> None:
    """Send a stored parameter set to the controller. Unattended runs send only a set an
    operator approved; a set the worker marked unfit (``uploadable: false``: worse than CAD,
    physically impossible) only when forced; every attempt is recorded; the controller's
    acknowledgement (or its absence: the set is withdrawn, the controller keeps its old one) is
    the outcome."""
    row = next((s for s in await store.param_sets(robot) if s["sha256"] == sha), None)
    if row is None:
        raise ConfigError(f"robot {robot}: no parameter set {sha[:12]}")
    if unattended and not row["approved"]:
        raise ApprovalError(f"unattended upload refused: parameter set {row['version']} of "
                            f"{robot} ({sha[:12]}) is not approved; run: robid params approve "
                            f"{row['version']} --robot {robot} --config C")
    body = json.loads(row["body"])
    if body.get("uploadable") is False and not force:
        raise ApprovalError(f"upload refused: parameter set {row['version']} of {robot} "
                            f"({sha[:12]}) is unfit: {'; '.join(body.get('unfit') or [])} — "
                            "or force it (robid campaign start NAME --force, campaign "
                            "force: true)")

    await store.record_upload(robot, sha, run_id, "sent")
    try:
        await driver.upload_parameters(body, timeout_s=timeout_s)
    except RobidError as err:
        await store.record_upload(robot, sha, run_id, "failed", str(err))
        raise
    await store.record_upload(robot, sha, run_id, "acknowledged")
    log.info("robot=%s parameter set %d (%s) loaded by the controller", robot, row["version"],
             sha[:12])
