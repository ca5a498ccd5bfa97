"""One layer process serving many twins: the event loop, the twins it learns, the twins it drops.

A layer's work for one twin is an object with ``poll(now) -> deadline | None``
(handle what has arrived for that twin without blocking; say when it next
needs to look even if nothing arrives) on a :class:`~dtpf.shell.service.ServiceShell`
of its own. :func:`serve_one` runs one such twin (a service started with the
twin's flags); :func:`serve_fleet` learns the twins under a key pattern from
their entities and runs each of them on the process's one Zenoh session:

- a twin is learned from its entity's Status (state ``starting``, with its
  run configuration), which the entity publishes before it waits for the
  layers and every second while it starts; the layer then declares
  ``dtpf/<twin>/<layer>/alive`` for that twin, which is what the entity waits
  for;
- a service that starts while its twins run (a restart), or whose link to
  them comes back, asks each entity's status publisher for its last status
  (Zenoh's history of an advanced publisher, :class:`ConfigWatch`) and serves
  again as soon as the answer comes, instead of waiting up to
  FLEET_STATUS_INTERVAL for the next status;
- a twin is dropped, its state freed, when its entity says it has finished or
  failed, when its entity's liveliness token goes after having been seen, or
  when its entity has not been seen for ``forget_after`` seconds;
- a new run of a twin replaces the old one.

Only built-in or registered models (no ``--model REF``) are served unless the
reference is in ``allow_models``: a status from the bus must not make a shared
service import code.
"""
from __future__ import annotations

import json
import logging
import signal
import threading
import time
from dataclasses import dataclass

from dtpf.messages import keys
from dtpf.messages.admission import kind_of
from dtpf.messages.codec import MessageError, decode_for_key
from dtpf.messages.config import RunConfig, RunInputError
from dtpf.messages.models import ServiceState, Status
from dtpf.shell.bus import Doorbell, Inbox, open_session
from dtpf.shell.service import EXIT_GRACE, ExitWatchdog, ServiceShell, Tally, release_memory

__all__ = ["serve_layer", "serve_one", "serve_run", "serve_fleet", "host_twins", "add_fleet_arguments", "ConfigWatch",
           "Learned", "twin_gone"]

#: Longest wait between two looks at the twins when nothing arrives.
_IDLE = 0.2
#: Most twins a fleet service serves at once; a status beyond them is counted, not served.
MAX_TWINS = 10_000
#: Most configurations (without their twin) a fleet service keeps validated.
_MAX_SHAPES = 64


def add_fleet_arguments(parser) -> None:
    """``--twins PATTERN`` and ``--allow-model REF``: serve every twin under a pattern."""
    group = parser.add_argument_group("fleet")
    group.add_argument("--twins", metavar="PATTERN", default=None,
                       help="serve every twin whose entity appears under this key chunk ('*' for all, 'line-1-*' "
                            "for some), each with the run configuration its entity announces; the run options "
                            "above are then ignored (default: serve only the twin of the run options)")
    group.add_argument("--allow-model", action="append", default=[], metavar="REF",
                       help="with --twins: a model reference (--model of a twin) this service may load; built-in "
                            "and registered scenarios need none (repeatable)")


def _wait_time(deadline: float | None, now: float) -> float:
    return _IDLE if deadline is None else min(_IDLE, max(0.0, deadline - now))


def serve_layer(layer: str, config: RunConfig, zenoh_config, args, load_model, make_work) -> int:
    """The ``main`` of a layer service: the twin of the run options, or (``--twins``) every twin under the
    pattern. ``load_model(config)`` gives a twin's model, ``make_work(shell, config, model)`` the layer's
    work for it; a model that cannot load stops a solo service before its session opens."""
    if args.twins:
        _warm_up(config, args.allow_model, load_model)
        serve_fleet(layer, args.twins, zenoh_config,
                    lambda shell, twin_config: make_work(shell, twin_config, load_model(twin_config)),
                    allow_models=args.allow_model)
        return 0
    model = load_model(config)
    doorbell = Doorbell()
    with ServiceShell(layer, config, zenoh_config, doorbell=doorbell) as shell:
        work = make_work(shell, config, model)
        shell.running()
        serve_one(shell, work, doorbell)
    return 0


def _warm_up(config: RunConfig, allow_models, load_model) -> None:
    """Load the model of the service's own run options (the fleet's, when a launcher starts it) before the
    service asks for its twins: the first twin of a model costs its loading (numba's compiled kernels, the
    configuration's validation), which would otherwise hold up every twin a restarted service learns at once.
    Only a built-in or allowed model; one that cannot load is for its twin to refuse later."""
    if config.model is not None and config.model not in allow_models:
        return
    try:
        RunConfig.model_validate_json(config.model_dump_json())
        load_model(config)
    except Exception as error:  # noqa: BLE001 - a warm-up: the twin that needs the model says what is wrong
        logging.getLogger("dtpf.fleet").debug("warm-up skipped: %s", error)


def serve_run(run, doorbell: Doorbell) -> int:
    """Poll one twin's ``run`` (a :func:`host_twins` run: ``poll(now)``, ``code``) whenever its inboxes or its
    peers ring, or its time comes, until it ends; returns its exit code."""
    while run.code is None:
        deadline = run.poll(time.monotonic())
        if run.code is None:
            doorbell.wait(_wait_time(deadline, time.monotonic()))
    return run.code


def serve_one(shell: ServiceShell, twin, doorbell: Doorbell) -> None:
    """Poll ``twin`` whenever its inboxes ring (or its deadline comes) until the shell stops; then its
    ``finish(doorbell)``, if it has one (what arrived before the stop is answered)."""
    while not shell.stopping:
        deadline = twin.poll(time.monotonic())
        doorbell.wait(_wait_time(deadline, time.monotonic()))
    finish = getattr(twin, "finish", None)
    if finish is not None:
        finish(doorbell)


@dataclass(frozen=True)
class Learned:
    """What an entity's status says of its twin: a run to serve, or the end of one."""

    twin: str
    config: RunConfig | None   #: the run to serve (None: the run ``run_id`` ended)
    run_id: str


class ConfigWatch:
    """The entities' statuses under a twin pattern, as the runs they announce and end.

    Every entity's status publisher keeps its last statuses (:func:`~dtpf.shell.bus.publisher`); the watch
    asks each one found for its last status when it starts and whenever the publisher appears again (its
    liveliness token back after a partition), so the twins already running are known within a round trip.
    """

    def __init__(self, session, pattern: str, on_reject):
        self.pattern = pattern
        self.on_reject = on_reject
        self.inbox = Inbox(session, f"{keys.PREFIX}/{keys.twins_chunk(pattern)}/entity/status",
                           max_payload=1 << 20, max_items=10_000, history=1,
                           max_bytes=64 << 20, on_drop=lambda key, reason, detail: on_reject(reason, detail))
        #: When each twin's entity was last heard (any status).
        self.heard: dict[str, float] = {}
        #: The configuration each twin's statuses carry, validated once (a status comes every few seconds).
        self._configs: dict[str, tuple[str, RunConfig]] = {}
        #: Configurations validated, by their JSON without the twin: a fleet's twins differ by their id only, and
        #: a restarted service learns them all at once (a validation each cost it about 10 ms a twin).
        self._validated: dict[str, RunConfig] = {}

    def poll(self, now: float, budget: int = 256) -> list[Learned]:
        """What the statuses that arrived say, at most ``budget`` of them (the rest at the next call)."""
        learned = []
        for _ in range(budget):
            item = self.inbox.get(timeout=0)
            if item is None:
                break
            try:
                status = decode_for_key(item.key, item.payload)
                if not isinstance(status, Status):
                    raise MessageError(f"expected Status, got {type(status).__name__}", key=item.key)
            except MessageError as error:
                self.on_reject(error.reason, str(error))
                continue
            if status.twin_id not in self.heard and len(self.heard) >= MAX_TWINS:
                self.on_reject("too many twins", f"{len(self.heard)} twins heard, at most {MAX_TWINS}")
                continue
            self.heard[status.twin_id] = now
            if status.state in (ServiceState.FINISHED, ServiceState.FAILED):
                learned.append(Learned(status.twin_id, None, status.run_id))
                continue
            if status.config_json is None:
                continue
            known = self._configs.get(status.twin_id)
            if known is not None and known[0] == status.config_json:
                config = known[1]
            else:
                try:
                    config = self._validate(status.config_json, status.twin_id)
                except ValueError as error:
                    self.on_reject("run configuration that does not validate", f"{item.key}: {str(error)[:300]}")
                    continue
                self._configs[status.twin_id] = (status.config_json, config)
            if config.twin != status.twin_id or config.run_id != status.run_id:
                self.on_reject("run configuration of another twin or run",
                               f"{item.key}: configuration of {config.twin}/{config.run_id}")
                continue
            learned.append(Learned(status.twin_id, config, status.run_id))
        return learned

    def _validate(self, config_json: str, twin: str) -> RunConfig:
        """The RunConfig of ``config_json``; one that differs from a configuration validated before only by its
        twin (whose id the status has validated) is that one for this twin. ValueError if it does not validate."""
        try:
            fields = json.loads(config_json)
        except ValueError as error:
            raise ValueError(f"not JSON: {error}") from None
        if not isinstance(fields, dict) or fields.get("twin") != twin:
            return RunConfig.model_validate_json(config_json)
        shape = json.dumps({name: value for name, value in fields.items() if name != "twin"}, sort_keys=True)
        known = self._validated.get(shape)
        if known is not None:
            return known.model_copy(update={"twin": twin})
        config = RunConfig.model_validate_json(config_json)
        if len(self._validated) >= _MAX_SHAPES:
            self._validated.clear()
        self._validated[shape] = config
        return config

    def forget(self, twin: str) -> None:
        self.heard.pop(twin, None)
        self._configs.pop(twin, None)

    def close(self) -> None:
        self.inbox.close()


def twin_gone(seen: set[str], alive: set[str], quiet: float, forget_after: float) -> str | None:
    """Why a fleet's twin is to be dropped, or None to go on serving it.

    ``seen`` and ``alive``: the layers of the twin whose liveliness token was ever seen, and is now
    (:class:`~dtpf.shell.bus.Presence`); ``quiet``: seconds since its entity's last status. The entity is
    gone once its token has been seen and is no more, whenever that was: a token that came and went while
    the service's loop was busy (a new twin's warm-up) had been missed by the loop's looks at ``alive``,
    and the twin waited ``forget_after`` to be freed. An entity whose token never came is forgotten after
    ``forget_after`` seconds without a status.
    """
    if "entity" in seen:
        return None if "entity" in alive else "its entity is gone"
    return f"its entity was not heard for {forget_after:.0f} s" if quiet > forget_after else None


class _Served:
    """One twin a fleet serves: its shell and its layer's work."""

    def __init__(self, shell: ServiceShell, work, run_id: str):
        self.shell = shell
        self.work = work
        self.run_id = run_id


def serve_fleet(layer: str, pattern: str, zenoh_config, make_work, *, allow_models=(), forget_after: float = 30.0,
                log: logging.Logger | None = None) -> None:
    """Serve every twin whose entity appears under ``pattern`` until SIGINT/SIGTERM.

    ``make_work(shell, config)`` builds the layer's work for a twin (it may
    raise ValueError or RunInputError: the twin is then refused and counted).
    A twin whose work waits (its ``poll`` returned a deadline) is looked at again at the next sweep, a few
    times a second, fine-grained enough for lockstep timeouts of seconds.
    """
    log = log or logging.getLogger(f"dtpf.{layer}")
    stop = threading.Event()

    def on_signal(signum, frame):
        log.info("received %s, stopping", signal.Signals(signum).name)
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    watchdog = ExitWatchdog(log, grace=EXIT_GRACE)
    watchdog.install()
    doorbell = Doorbell()
    refusals = Tally()

    def refuse(reason: str, detail: str | None = None) -> None:
        if refusals.add(kind_of(reason)):
            log.warning("refused (%s; further ones of this kind are counted): %s", kind_of(reason),
                        (detail or reason)[:500])

    session = open_session(zenoh_config)
    watch = ConfigWatch(session, pattern, refuse)
    log.info("serving the twins under %r: asked their entities for their last status", pattern)
    served: dict[str, _Served] = {}

    trim = {"due": False}

    def drop(twin: str, why: str) -> None:
        entry = served.pop(twin)
        entry.shell.__exit__(None, None, None)
        watch.forget(twin)
        trim["due"] = True  # the twin's buffers go back to the system at the next sweep
        log.info("twin %s: %s; its state is freed (%d twins served)", twin, why, len(served))

    def serve(config: RunConfig) -> None:
        if config.model is not None and config.model not in allow_models:
            refuse("model not allowed", f"twin {config.twin}: model {config.model!r} is not in --allow-model; "
                                        "a fleet service loads only built-in and registered models by itself")
            return
        began = time.monotonic()
        shell = ServiceShell(layer, config, session=session, doorbell=doorbell).__enter__()
        try:
            work = make_work(shell, config)
        except (ValueError, OSError) as error:
            shell.state = ServiceState.FAILED
            shell.last_error = str(error)[:500]
            shell.__exit__(None, None, None)
            refuse("twin that cannot be served", f"twin {config.twin}: {error}")
            return
        shell.running()
        served[config.twin] = _Served(shell, work, config.run_id)
        log.info("twin %s: serving run %s (%d twins served; its state built in %.2f s)", config.twin, config.run_id,
                 len(served), time.monotonic() - began)

    try:
        rung: set[str] = set()
        next_sweep = 0.0
        while not stop.is_set():
            now = time.monotonic()
            for event in watch.poll(now):
                entry = served.get(event.twin)
                if event.config is None:
                    if entry is not None and entry.run_id == event.run_id:
                        drop(event.twin, "its entity finished")
                    continue
                if entry is not None and entry.run_id == event.config.run_id:
                    continue
                if entry is not None:
                    drop(event.twin, f"a new run {event.config.run_id} replaces run {entry.run_id}")
                serve(event.config)
            if now >= next_sweep:  # liveness and statuses of every twin, a few times a second
                next_sweep = now + _IDLE
                if trim["due"]:
                    trim["due"] = False
                    release_memory()
                for twin, entry in list(served.items()):
                    presence = entry.shell.presence
                    why = twin_gone(presence.seen, presence.alive, now - watch.heard.get(twin, now), forget_after)
                    if why is not None:
                        drop(twin, why)
                        continue
                    entry.shell.tick(now)
                    rung.add(twin)  # a deadline may have passed
            for twin in rung:
                entry = served.get(twin)
                if entry is not None:
                    entry.work.poll(now)
            rung = doorbell.wait(_IDLE)
    finally:
        watchdog.arm(code=0)
        for twin in list(served):
            drop(twin, "the service stops")
        watch.close()
        session.close()


def host_twins(layer: str, configs: list[RunConfig], zenoh_config, make) -> int:
    """Run each twin of ``configs`` on one Zenoh session in one event loop (an entity hosting several twins).

    ``make(shell, config)`` gives a twin's run: an object whose ``poll(now)`` does
    what can be done without blocking and returns when to look again (None:
    when something arrives; a time already passed: at once), and whose
    ``code`` is its exit code once it has ended. A twin polls when its inboxes
    or its peers ring, or its time comes; the statuses of every twin go out
    every second while it starts (a starting entity's status is how a
    fleet's shared layers learn it), every FLEET_STATUS_INTERVAL after. A
    twin whose model or file is wrong (RunInputError) ends with 2, one that
    fails with a bug of ours with 1; the others go on.
    SIGINT/SIGTERM stop them all. Returns the largest exit code of the twins.

    One thread for all the twins: with a thread each, every twin-step handed
    the GIL between the twins' threads (numpy and the compiled kernels release
    it) and the process switched context hundreds of times a twin-step.
    """
    log = logging.getLogger(f"dtpf.{layer}")
    session = open_session(zenoh_config)
    doorbell = Doorbell()
    shells = {config.twin: ServiceShell(layer, config, session=session, doorbell=doorbell) for config in configs}

    def on_signal(signum, frame):
        log.info("received %s, stopping %d twins", signal.Signals(signum).name, len(shells))
        for shell in shells.values():
            shell.stop()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    watchdog = ExitWatchdog(log, grace=EXIT_GRACE)
    watchdog.install()
    codes: dict[str, int] = {}
    runs: dict[str, object] = {}

    def end(twin: str, code: int, exc: BaseException | None = None) -> None:
        codes[twin] = code
        runs.pop(twin, None)
        shells[twin].__exit__(type(exc) if exc else None, exc, None)

    def guarded(twin: str, action):
        try:
            return action()
        except RunInputError as error:
            log.error("twin %s: %s", twin, error)
            end(twin, 2, error)
        except Exception as error:  # a bug of ours: this twin fails, the others go on
            log.exception("twin %s failed", twin)
            end(twin, 1, error)
        return None

    for twin, shell in shells.items():
        shell.__enter__()
        made = guarded(twin, lambda: make(shell, shell.config))
        if made is not None:
            runs[twin] = made
    due: dict[str, float] = {twin: 0.0 for twin in runs}  # when each twin next wants a look
    rung: set[str] = set(runs)
    next_tick = 0.0
    while runs:
        now = time.monotonic()
        if now >= next_tick:
            next_tick = now + _IDLE
            for shell in shells.values():
                if shell.config.twin in runs:
                    shell.tick(now)
        rung |= {twin for twin, when in due.items() if when <= now}
        for twin in rung:
            run = runs.get(twin)
            if run is None:
                continue
            wake = guarded(twin, lambda: run.poll(now))
            if twin not in runs:
                due.pop(twin, None)
            elif run.code is not None:
                end(twin, run.code)
                due.pop(twin, None)
            else:
                due[twin] = now + _IDLE if wake is None else wake
        if not runs:
            break
        rung = doorbell.wait(_wait_time(min(due.values(), default=None), time.monotonic()))
    code = max(codes.values(), default=1)
    watchdog.arm(code=code)
    session.close()
    return code
