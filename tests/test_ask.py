"""Ask the twin: its state now, its history, its forecast, over Zenoh queries (docs/guides/ask.md).

Pure parts first (selectors, the forecast's numbers and statistics), then one live twin serving every
check: an entity filtering live observations and a recorder, on a router of this test; the entity's
state between observations, its forecast twice and against the recorded particle set, garbage and a
storm of queries; then the finished log under ``dtpf serve``, whose history is ``dtpf cat``'s.
"""
from __future__ import annotations

import json
import math
import os
import signal
import sys
import time

import numpy as np
import pytest

from conftest import Processes, Router, service_args
from dtpf.entity.forecast import forecast, forecast_stream
from dtpf.entity.models import DriftModel, get as get_model
from dtpf.messages import queries
from dtpf.messages.codec import encode
from dtpf.messages.models import Estimate, Observation
from dtpf.messages.streams import stream
from dtpf.shell.bus import BusError, free_port, open_session, zenoh_config
from dtpf.shell.queries import ask

#: Deadlines for a loaded 2-core machine (a service's start imports numpy and numba: seconds).
START, ANSWER = 90.0, 10.0
TWIN, RUN_ID, SEED, N = "t-ask", "ask", 4, 200


# --- pure parts ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind, text, says", [
    ("history", "steps=a", "steps must be A:B"),
    ("history", "steps=5:3", "need A <= B"),
    ("history", "limit=0", "limit=0 is out of bounds"),
    ("history", f"limit={queries.MAX_LIMIT + 1}", f"at most {queries.MAX_LIMIT}"),
    ("history", "time=x:1", "time must be a number"),
    ("history", "topics=a b", "is no topic"),
    ("history", "steps=1;steps=2", "given twice"),
    ("forecast", "horizon=0", "at least 1"),
    ("forecast", "horizon=" + "9" * 30, "must be an integer"),
    ("forecast", "dt=nan", "finite"),
    ("state", "particles=maybe", "true or false"),
    ("state", "drop=table", "unknown state parameter 'drop'"),
    ("state", "x" * (queries.MAX_SELECTOR_TEXT + 1), "at most"),
    ("state", ";".join(f"p{i}=1" for i in range(queries.MAX_PARAMETERS + 1)), "more than"),
])
def test_a_bad_selector_is_one_line_naming_what_is_wrong(kind, text, says):
    with pytest.raises(queries.SelectorError, match=says) as caught:
        queries.parse(kind, text)
    assert "\n" not in str(caught.value)


def test_any_text_is_a_selector_or_a_selector_error():
    rng = np.random.default_rng(1)
    alphabet = list("=;&:,|*/.-_ab01xyz%\x00\u00e9") + ["steps", "time", "topics", "limit", "horizon", "particles"]
    for _ in range(2000):
        text = "".join(rng.choice(alphabet, size=rng.integers(0, 30)))
        for kind in queries.KINDS:
            try:
                queries.parse(kind, text)
            except queries.SelectorError:
                pass


def test_a_forecast_is_the_same_numbers_twice_and_draws_none_of_the_runs_numbers():
    model, rng = get_model("ungm"), np.random.default_rng(3)
    x, w = rng.normal(size=(500, 1)), rng.dirichlet(np.ones(500))
    kept = x.copy()
    first = forecast(model, x, w, 7, 6, seed=SEED, twin=TWIN)
    again = forecast(model, x, w, 7, 6, seed=SEED, twin=TWIN)
    shorter = forecast(model, x, w, 7, 3, seed=SEED, twin=TWIN)
    np.testing.assert_array_equal(x, kept)  # the set given is not changed
    for name in ("mean", "var", "lower", "upper"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
        np.testing.assert_array_equal(getattr(first, name)[:3], getattr(shorter, name))
    assert first.steps.tolist() == [8, 9, 10, 11, 12, 13]
    # Its streams are none of the run's: the entity's of step 8 propagates the set elsewhere.
    by_run = model.propagate(x.copy(), 8, stream(SEED, TWIN, 8, "entity"))
    assert not np.allclose(w @ by_run, first.mean[0])
    assert forecast_stream(SEED, TWIN, 7, 1).random() != stream(SEED, TWIN, 7, "entity").random()


def _mixture_cdf(q: float, h: float) -> float:
    return 0.3 * 0.5 * (1 + math.erf(q / math.sqrt(2 * h))) + 0.7 * 0.5 * (1 + math.erf((q - 10) / math.sqrt(2 * h)))


def _mixture_quantile(p: float, h: float) -> float:
    low, high = -50.0, 60.0
    for _ in range(100):
        mid = (low + high) / 2
        low, high = (mid, high) if _mixture_cdf(mid, h) < p else (low, mid)
    return (low + high) / 2


def test_a_forecast_of_a_random_walk_has_the_moments_and_band_of_its_predictive_law():
    """Particles half at 0 (weight 0.3 in all), half at 10 (0.7), a random walk of unit steps: at horizon h the
    predictive law is 0.3 N(0, h) + 0.7 N(10, h), mean 7, variance 21 + h. Tolerances: 5 sd of each estimate
    over the walk's noise (weighted sums of independent normals)."""
    n = 4000
    x = np.repeat([0.0, 10.0], n // 2)[:, None]
    w = np.repeat([0.3, 0.7], n // 2) / (n // 2)
    ahead = forecast(DriftModel(process_var=1.0), x, w, 1, 4, seed=11, twin=TWIN)
    sum_w2 = float(w @ w)
    offsets = x[:, 0] - 7.0
    for h in (1, 4):
        mean_sd = math.sqrt(h * sum_w2)
        assert abs(ahead.mean[h - 1, 0] - 7.0) < 5 * mean_sd
        var_sd = math.sqrt(float((w * w) @ (4 * offsets ** 2 * h + 2 * h * h)))
        assert abs(ahead.var[h - 1, 0] - (21.0 + h)) < 5 * var_sd + 5 * mean_sd * 2 * 7
        for p, got in ((0.025, ahead.lower[h - 1, 0]), (0.975, ahead.upper[h - 1, 0])):
            q = _mixture_quantile(p, h)
            density = (0.3 * math.exp(-q * q / (2 * h)) + 0.7 * math.exp(-(q - 10) ** 2 / (2 * h))) / math.sqrt(2 * math.pi * h)
            assert abs(got - q) < 5 * math.sqrt(p * (1 - p) * sum_w2) / density, (h, p, got, q)


class _Walk(DriftModel):
    """A driven random walk: x_k = x_(k-1) + dt + sqrt(dt) u (a unit velocity, Brownian noise)."""

    def propagate(self, particles, k, rng, noise=None, *, dt):
        return particles + dt + math.sqrt(dt) * rng.standard_normal(particles.shape)


def test_a_horizon_in_seconds_is_steps_of_dt_the_last_one_shorter():
    from dtpf.entity.forecast import ForecastError, seconds_steps

    selector = queries.parse("forecast", "horizon_s=2;dt=0.3")
    assert selector.horizon == 7 and selector.horizon_s == 2.0
    steps, dts = seconds_steps(2.0, 0.3)
    assert steps == 7 and math.isclose(sum(dts), 2.0) and math.isclose(dts[-1], 0.2)
    x, w = np.zeros((2000, 1)), np.full(2000, 1 / 2000)
    ahead = forecast(_Walk(), x, w, 5, steps, dts, seed=SEED, twin=TWIN)
    assert np.allclose(ahead.seconds, np.cumsum(dts)) and ahead.steps.tolist() == list(range(6, 13))
    # At 2 s the walk's law is N(2, 2): the mean within 5 sd of its estimate over N particles.
    assert abs(ahead.mean[-1, 0] - 2.0) < 5 * math.sqrt(2.0 / 2000)
    assert ahead.points()[-1]["seconds"] == pytest.approx(2.0)
    for text, says in (("horizon_s=2", "needs dt="), ("horizon_s=2;horizon=3;dt=1", "not both"),
                       ("horizon_s=0;dt=1", "> 0"), ("horizon_s=1e6;dt=0.001", "at most")):
        with pytest.raises(queries.SelectorError, match=says):
            queries.parse("forecast", text)
    with pytest.raises(ForecastError, match="at most"):
        seconds_steps(1e6, 1e-3)


class _BlockingShell:
    """A shell whose first publish waits for ``release``: the publisher's thread is busy meanwhile."""

    def __init__(self):
        import threading

        self.entered, self.release, self.published = threading.Event(), threading.Event(), []
        self.log, self.stopping = None, False

    def header(self, step):
        return {"run_id": RUN_ID, "twin_id": TWIN, "step": step}

    def publish(self, message):
        self.entered.set()
        self.release.wait(ANSWER)
        self.published.append(message)


def test_each_steps_forecast_is_published_off_the_filters_path_skipping_a_step_rather_than_waiting():
    from types import SimpleNamespace

    from dtpf.entity.answers import ForecastPublisher, _Latest
    from dtpf.messages.models import ForecastBand

    shell, model = _BlockingShell(), get_model("ungm")
    rng = np.random.default_rng(2)
    sets = {k: (rng.normal(size=(100, 1)), rng.dirichlet(np.ones(100))) for k in range(1, 5)}
    publisher = ForecastPublisher(shell, SimpleNamespace(twin=TWIN, seed=SEED), model, 3)
    try:
        publisher.offer(_Latest(1, {}, 0, *sets[1]))
        assert shell.entered.wait(ANSWER)
        for k in (2, 3, 4):  # the thread is busy with step 1: each offer returns at once, 2 and 3 are skipped
            publisher.offer(_Latest(k, {}, 0, *sets[k]))
        assert publisher.skipped == 2
        shell.release.set()
        wait_until(lambda: len(shell.published) == 2, ANSWER, "the forecasts of steps 1 and 4")
    finally:
        publisher.close()
    assert [m.step for m in shell.published] == [1, 4] and all(isinstance(m, ForecastBand) for m in shell.published)
    ahead = forecast(model, *sets[4], 4, 3, seed=SEED, twin=TWIN)
    assert [p.upper for p in shell.published[1].ahead] == ahead.upper.tolist()
    assert [p.step for p in shell.published[1].ahead] == [5, 6, 7]


def test_the_foxglove_layout_draws_the_forecast_band_and_docs_holds_the_one_dtpf_layout_writes():
    pytest.importorskip("foxglove")
    from conftest import ROOT
    from dtpf.scripts.foxglove_layout import layout_json

    written = json.loads(layout_json("ungm-1"))
    assert json.loads((ROOT / "docs" / "foxglove-layout.json").read_text()) == written
    assert '"dtpf/ungm-1/entity/forecast_band".ahead[:].step' in json.dumps(written).replace('\\"', '"')


def test_the_calibration_tables_interval_and_a_small_run(capsys):
    from dtpf.scripts.paper import forecast_calibration as calibration

    low, high = calibration.wilson(950, 1000)  # the Wilson interval of 95% of 1000: 0.935 .. 0.962
    assert (round(low, 3), round(high, 3)) == (0.935, 0.962)
    assert calibration.wilson(0, 10)[0] == 0.0 and calibration.wilson(10, 10)[1] == pytest.approx(1.0)
    assert calibration.main(["--seeds", "4", "--steps", "5", "--particles", "200", "--scenarios", "drift"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| drift")]
    assert len(rows) == 1 and rows[0].count("(") == len(calibration.HORIZONS)
    assert calibration.main(["--seeds", "0"]) == 2


def test_a_driven_twin_answers_a_horizon_in_seconds_and_publishes_with_its_last_steps_dt():
    import logging
    from types import SimpleNamespace

    from dtpf.entity.answers import ForecastPublisher, LiveAnswers
    from dtpf.entity.timeline import Drive

    shell = SimpleNamespace(session=None, log=logging.getLogger("test-ask"), state=SimpleNamespace(value="running"),
                            detail=None, header=lambda step: {"run_id": RUN_ID, "twin_id": TWIN, "step": step})
    config = SimpleNamespace(twin=TWIN, seed=SEED)
    answers = LiveAnswers(shell, config, _Walk())  # no session: no queryables, the answers all the same
    x, w = np.zeros((500, 1)), np.full(500, 1 / 500)
    answers.keep(SimpleNamespace(step=9, particles=x, weights=w, drive=Drive(np.array([[0.25]]))), {})
    answer = json.loads(answers.answer_forecast("", "horizon_s=1;dt=0.3"))
    assert [entry["step"] for entry in answer["steps"]] == [10, 11, 12, 13]
    assert [entry["seconds"] for entry in answer["steps"]] == pytest.approx([0.3, 0.6, 0.9, 1.0])
    publisher = ForecastPublisher(shell, config, _Walk(), 2)
    try:
        first = answers.latest.__class__(1, {}, 0, x, w, None)
        assert publisher.message(first) is None  # a driven twin's first step has no dt: nothing to publish
        band = publisher.message(answers.latest)  # steps of the last step's 0.25 s: the mean moves 0.25 a step
        assert [p.step for p in band.ahead] == [10, 11]
        assert abs(band.ahead[1].mean[0] - 0.5) < 5 * math.sqrt(0.5 / 500)
        same_stamp = answers.latest.__class__(10, {}, 0, x, w, 0.0)  # two observations of one stamp: dt 0
        expected = forecast(_Walk(), x, w, 10, 2, seed=SEED, twin=TWIN, dt=0.25)  # the last dt above zero
        assert [p.mean for p in publisher.message(same_stamp).ahead] == expected.mean.tolist()
    finally:
        publisher.close()
    with pytest.raises(queries.SelectorError, match="takes no dt"):
        _ungm_answers(shell, config, x, w).answer_forecast("", "horizon_s=1;dt=0.5")


def _ungm_answers(shell, config, x, w):
    from types import SimpleNamespace

    from dtpf.entity.answers import LiveAnswers

    answers = LiveAnswers(shell, config, get_model("ungm"))
    answers.keep(SimpleNamespace(step=2, particles=x, weights=w, drive=None), {})
    return answers


# --- one live twin ---------------------------------------------------------------------------------------

def wait_until(condition, timeout: float, what: str):
    until = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        assert time.monotonic() < until, f"not within {timeout:.0f} s: {what}"
        time.sleep(0.1)


class LiveTwin:
    """A live entity and a recorder of TWIN on a router of this test; ``messages`` decoded from the router."""

    def __init__(self, tmp):
        self.log_path = tmp / "run.mcap"
        self.processes = Processes(tmp)
        self.router = Router()
        run = ["--twin", TWIN, "--run-id", RUN_ID, "--seed", str(SEED), "--particles", str(N), "--observations", "live"]
        self.recorder = self.processes.start("recorder", service_args("dtpf.scripts.record", self.router.endpoint,
                                                                      *run, "-o", str(self.log_path)))
        # Preprocessing on with no information layer: the entity publishes each step's particle set and goes on.
        self.entity = self.processes.start("entity", service_args("dtpf.entity.service", self.router.endpoint, *run,
                                                                  "--startup-timeout", "0", "--cloud-points", "0",
                                                                  "--forecast", "3"))
        self.session = self.router.session
        self.sensor = self.session.declare_publisher(f"dtpf/{TWIN}/sensor/observation")

    def ask(self, kind: str, text: str = "", timeout: float = ANSWER):
        return ask(self.session, queries.key(TWIN, kind), text, timeout=timeout)

    def observe(self, step: int, value: float | None = None, end: bool = False) -> None:
        self.sensor.put(encode(Observation(run_id=RUN_ID, twin_id=TWIN, step=step, end=end,
                                           values=[] if end else [value])))

    def estimate(self, step: int) -> Estimate | None:
        return next((m for m in self.router.messages if isinstance(m, Estimate) and m.step == step), None)

    def close(self) -> None:
        self.processes.stop_all()
        self.router.close()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    twin = LiveTwin(tmp_path_factory.mktemp("ask"))
    try:
        # Both are up once both answer (the entity: "no estimate yet"; the recorder: its first flush).
        wait_until(lambda: twin.ask("state", timeout=2).errors, START, "the entity answers")
        wait_until(lambda: twin.ask("history", timeout=2).answers, START, "the recorder answers")
        for step, value in ((1, 0.5), (2, 3.0), (3, -1.0)):
            twin.observe(step, value)
        assert twin.router.collect(lambda messages: twin.estimate(3) is not None, START), twin.processes.output(twin.entity)
        yield twin
    finally:
        twin.close()


def test_a_live_twin_answers_its_state_between_observations(live):
    before = live.ask("state").errors
    answer = live.ask("state", "particles=true").first()
    published = live.estimate(3)
    assert answer["step"] == 3 and answer["twin"] == TWIN
    estimate = Estimate.model_validate(answer["estimate"])
    assert (estimate.mean, estimate.var, estimate.ess, estimate.degraded) == \
        (published.mean, published.var, published.ess, published.degraded)
    assert len(answer["particles"]) == N and abs(sum(answer["weights"]) - 1) < 1e-9
    too_big = live.ask("state", "particles=true;max_bytes=1000").errors
    assert len(too_big) == 1 and "more than max_bytes=1000" in too_big[0]
    assert before == [] and live.entity.poll() is None


def test_a_forecast_is_the_same_twice_and_propagates_the_recorded_set_of_its_step(live):
    first = live.ask("forecast", "horizon=4").first()
    again = live.ask("forecast", "horizon=4").first()
    assert first == again and first["from_step"] == 3
    recorded = wait_until(lambda: live.ask("history", "steps=3;topics=entity/particles").first()["messages"],
                          ANSWER * 3, "the recorder holds the particle set of step 3")
    assert len(recorded) == 1
    particles, weights = np.array(recorded[0]["message"]["particles"]), np.array(recorded[0]["message"]["weights"])
    ahead = forecast(get_model("ungm"), particles, weights, 3, 4, seed=SEED, twin=TWIN)
    assert [entry["mean"] for entry in first["steps"]] == ahead.mean.tolist()
    assert [entry["upper"] for entry in first["steps"]] == ahead.upper.tolist()


def test_each_steps_forecast_band_is_published_recorded_and_the_forecast_of_its_set(live):
    from dtpf.messages.models import ForecastBand

    recorded = wait_until(lambda: live.ask("history", "steps=3;topics=entity/forecast_band,entity/particles")
                          .first()["messages"], ANSWER * 3, "the recorder holds the forecast band of step 3")
    by_topic = {entry["topic"].rpartition("/")[2]: entry["message"] for entry in recorded}
    band = ForecastBand.model_validate(by_topic["forecast_band"])
    def heard_band(messages):
        return next((m for m in messages if isinstance(m, ForecastBand) and m.step == 3), None)

    assert live.router.collect(heard_band, ANSWER * 3), "the router heard the forecast band of step 3"
    heard = heard_band(live.router.messages)
    assert heard == band and [p.step for p in band.ahead] == [4, 5, 6]
    particles = np.array(by_topic["particles"]["particles"])
    ahead = forecast(get_model("ungm"), particles, np.array(by_topic["particles"]["weights"]), 3, 3, seed=SEED,
                     twin=TWIN)
    assert [p.mean for p in band.ahead] == ahead.mean.tolist()
    assert [p.lower for p in band.ahead] == ahead.lower.tolist()


def test_garbage_selectors_get_error_replies_and_the_twin_runs_on(live):
    for kind, text in (("state", "particles=maybe"), ("forecast", "horizon=-1"), ("forecast", "control=1"),
                       ("forecast", f"horizon={queries.MAX_HORIZON + 1}"), ("history", "steps=;;=;"),
                       ("history", "\x00\xff" * 600)):
        replies = live.ask(kind, text)
        assert replies.answers == [] and len(replies.errors) == 1, (kind, text, replies)
    live.observe(4, 2.0)
    assert live.router.collect(lambda messages: live.estimate(4) is not None, START)
    assert live.ask("state").first()["step"] == 4 and live.entity.poll() is None


def test_a_storm_of_questions_is_bounded_by_the_rate_and_refused_with_a_reason(live):
    from dtpf.entity.answers import STATE_BURST, STATE_RATE

    asked = 3 * STATE_BURST
    start = time.monotonic()
    handlers = [live.session.get(queries.key(TWIN, "state"), timeout=ANSWER * 3) for _ in range(asked)]
    answered = refused = 0
    for handler in handlers:
        for reply in handler:
            if reply.ok is not None:
                answered += 1
                assert len(reply.ok.payload.to_bytes()) < 64 << 10
            else:
                text = reply.err.payload.to_bytes().decode()
                assert "too many queries" in text or "busy" in text, text
                refused += 1
    elapsed = time.monotonic() - start
    assert answered + refused == asked
    assert answered <= STATE_BURST + STATE_RATE * elapsed + 1
    if asked > STATE_BURST + STATE_RATE * elapsed + 1:
        assert refused > 0
    wait_until(lambda: live.ask("state").answers, ANSWER * 3, "the twin answers again after the storm")


@pytest.fixture(scope="module")
def finished(live):
    """The live twin ended (its sensor's last word), its recorder stopped: the finished log."""
    if live.estimate(4) is None:  # the tests before may not have run (-k)
        live.observe(4, 2.0)
        assert live.router.collect(lambda messages: live.estimate(4) is not None, START)
    running = wait_until(lambda: (lambda answer: answer if answer["count"] == 4 else None)(
        live.ask("history", "steps=1:4").first()), ANSWER * 3, "the recorder holds the estimate of step 4")
    live.observe(5, end=True)
    assert live.entity.wait(timeout=START) == 0, live.processes.output(live.entity)
    os.kill(live.recorder.pid, signal.SIGINT)
    assert live.recorder.wait(timeout=START) == 0, live.processes.output(live.recorder)
    return live.log_path, running


def _cat(log, *args) -> list[dict]:
    import subprocess

    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "cat", str(log), *args, "--json"],
                          capture_output=True, text=True, timeout=START)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()]


def _client(endpoint: str):
    try:
        return open_session(zenoh_config(mode="client", connect=[endpoint]))
    except BusError:
        return None


@pytest.fixture(scope="module")
def served(finished, live):
    log, _ = finished
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    process = live.processes.start("serve", ["-m", "dtpf.scripts.cli", "serve", str(log), "--listen", endpoint])
    session = wait_until(lambda: _client(endpoint) or process.poll() is not None, START, "dtpf serve listens")
    assert process.poll() is None, live.processes.output(process)
    try:
        wait_until(lambda: ask(session, queries.key(TWIN, "history"), timeout=2).answers or process.poll() is not None,
                   START, "dtpf serve answers")
        assert process.poll() is None, live.processes.output(process)
        yield endpoint, session, process
    finally:
        session.close()


def test_history_from_the_running_recorder_and_from_dtpf_serve_equals_dtpf_cat(finished, served):
    log, running = finished
    endpoint, session, _ = served
    assert running["messages"] == _cat(log, "--steps", "1:4", "--topics", "entity/estimate")
    import subprocess

    done = subprocess.run([sys.executable, "-m", "dtpf.scripts.cli", "ask", TWIN, "history", "--steps", "2:3",
                           "--topics", "entity/estimate", "entity/particles", "--connect", endpoint, "--json"],
                          capture_output=True, text=True, timeout=START)
    assert done.returncode == 0, done.stderr
    answer = json.loads(done.stdout)
    assert answer["messages"] == _cat(log, "--steps", "2:3", "--topics", "entity/estimate", "entity/particles")
    assert answer["count"] == 4


def test_a_history_answer_chooses_what_dtpf_cat_chooses_and_its_index_follows_a_growing_log(finished):
    from dataclasses import replace

    from dtpf.recording.logfile import read_log
    from dtpf.scripts.logs.history import StepIndex, history_entries
    from dtpf.scripts.logs.select import StepRange, as_json, choose

    log = read_log(finished[0])
    times = sorted(item.log_time for item in log.messages)
    middle = f"{times[len(times) // 3] / 1e9:.9f}:{times[2 * len(times) // 3] / 1e9:.9f}"
    index = StepIndex()
    first = replace(log, messages=log.messages[: len(log.messages) // 2])  # the log as a recorder read it earlier
    assert history_entries(first, TWIN, queries.parse("history", "steps=1:2;particles=true"), index)
    for text, steps, topics in (("steps=2:3", "2:3", ["entity/estimate"]), ("", None, ["entity/estimate"]),
                                ("steps=4;topics=*/entity/*", "4", ["*/entity/*"]),
                                (f"time={middle};topics=dtpf/*/*/*", None, ["dtpf/*/*/*"])):
        selector = queries.parse("history", text)
        expected = [{"topic": item.topic, "log_time": item.log_time, "message": as_json(message)}
                    for item, message in choose(log, topics=topics, steps=steps and StepRange(steps), twin=TWIN,
                                                keep_run_level=False) if selector.holds_time(item.log_time)]
        assert history_entries(log, TWIN, selector, index) == expected, text
        assert expected, text


def test_dtpf_serve_refuses_what_breaks_a_bound_or_is_garbage_and_serves_on(served):
    endpoint, session, process = served
    key = queries.key(TWIN, "history")
    too_many = ask(session, key, "steps=1:5;limit=2").errors
    assert too_many and "limit=2" in too_many[0]
    too_big = ask(session, key, "particles=true;max_bytes=100").errors
    assert too_big and "max_bytes=100" in too_big[0]
    for text in ("steps=x", "nonsense", "time=:", "limit=-1", "topics=" + "a" * 500):
        assert len(ask(session, key, text).errors) == 1, text
    for text in ("&&&===", ";" * 3000, "%ff%00=1"):  # what Zenoh makes of them, answered or refused
        replies = ask(session, key, text)
        assert len(replies.answers) + len(replies.errors) == 1, text
    assert ask(session, key, "steps=4").first()["count"] == 1 and process.poll() is None
    assert ask(session, queries.key("t-other", "history"), timeout=2).answers == []


def test_under_access_control_the_readers_ask_and_only_the_entity_and_the_recorder_answer(tmp_path):
    """The rules of dtpf secure init: a viewer's questions reach the entity's and the recorder's queryables; a
    sensor's are dropped, and a queryable a sensor declares (forged answers) is never asked."""
    pytest.importorskip("cryptography")
    from dtpf.scripts import secure
    from dtpf.shell.queries import Queryable
    from dtpf.shell.secure import open_secure_dir

    secure.init(tmp_path / "deploy")
    folder = open_secure_dir(tmp_path / "deploy" / "tls")
    endpoint = folder.endpoint("127.0.0.1", free_port())
    sessions = [open_session(zenoh_config(secure=folder, role="router", listen=[endpoint]))]
    try:
        role = {name: open_session(zenoh_config(secure=folder, role=name, connect=[endpoint]))
                for name in ("entity", "recorder", "viewer", "sensor")}
        sessions += role.values()
        answering = [Queryable(role["entity"], queries.key(TWIN, "state"), lambda key, text: b'{"by": "entity"}'),
                     Queryable(role["recorder"], queries.key(TWIN, "history"), lambda key, text: b'{"by": "recorder"}'),
                     Queryable(role["sensor"], queries.key(TWIN, "forecast"), lambda key, text: b'{"by": "sensor"}')]
        state = wait_until(lambda: ask(role["viewer"], queries.key(TWIN, "state"), timeout=2).answers, START,
                           "the viewer's question reaches the entity")
        assert [body for _, body in state] == [{"by": "entity"}]
        assert ask(role["viewer"], queries.key(TWIN, "history"), timeout=2).first() == {"by": "recorder"}
        assert ask(role["viewer"], queries.key(TWIN, "forecast"), timeout=2).answers == []
        assert ask(role["sensor"], queries.key(TWIN, "state"), timeout=2).answers == []
        for queryable in answering:
            queryable.close()
    finally:
        for session in sessions:
            session.close()


def test_a_particle_set_that_cannot_fit_is_refused_before_it_is_built():
    """Every float takes at least 4 bytes of JSON ("0.0,"): a set of more numbers than max_bytes / 4 is refused
    from its size alone, never turned into a list (a million particles asked with the default bound)."""
    assert len(json.dumps([0.0] * 251, separators=(",", ":"))) > 1000  # the least 251 floats can weigh
    queries.check_values(250, 1000)
    with pytest.raises(queries.SelectorError, match="251 numbers, at least 1004 bytes of JSON, more than max_bytes=1000"):
        queries.check_values(251, 1000)
    with pytest.raises(queries.SelectorError, match="more than max_bytes"):
        queries.check_values(2_000_000, queries.DEFAULT_MAX_BYTES)
