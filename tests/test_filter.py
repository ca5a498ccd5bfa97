"""Models, the filter iterator and the in-process pipeline."""
import math

import numpy as np
import pytest

from dtpf.entity import models
from dtpf.entity.filter import FilterError, ParticleFilter, Preprocessed
from dtpf.messages.config import RunConfig
from dtpf.messages.streams import stream
from dtpf.scripts import inprocess

# --- models ----------------------------------------------------------------------

def test_growth_models_have_distinct_names_and_constants():
    assert models.get("ungm").growth == 25.0
    assert models.get("ungm-printed").growth == 0.25
    with pytest.raises(ValueError, match="unknown model 'ungm25'; expected one of ungm, ungm-printed"):
        models.get("ungm25")


def test_simulation_follows_eq35_and_eq36():
    model = models.get("ungm")
    truth, z = model.simulate(100, np.random.default_rng(0))
    assert truth.shape == (100, 1) and z.shape == (100, 1)
    assert truth[0, 0] == 0.1
    drift = np.array([model.transition_mean(truth[k - 2], k)[0] for k in range(2, 101)])
    process_noise = truth[1:, 0] - drift
    observation_noise = z[:, 0] - truth[:, 0] ** 2 / 20
    # Sample variances of 99 / 100 normal draws: standard error sigma^2 sqrt(2 / (n - 1)).
    assert abs(process_noise.var() - 10.0) <= 5 * 10.0 * math.sqrt(2 / 98)
    assert abs(observation_noise.var() - 1.0) <= 5 * 1.0 * math.sqrt(2 / 99)


def test_the_two_growth_forms_differ():
    rng = np.random.default_rng
    a, _ = models.get("ungm").simulate(20, rng(1))
    b, _ = models.get("ungm-printed").simulate(20, rng(1))
    assert not np.allclose(a[1:], b[1:])


# --- filter ------------------------------------------------------------------------

def bootstrap_reference(z, n, seed, model):
    """An independent bootstrap filter: numpy only, multinomial resampling with rng.choice."""
    rng = np.random.default_rng(seed)
    x = rng.normal(model.prior_mean, math.sqrt(model.prior_var), n)
    means = []
    for k in range(1, len(z) + 1):
        if k > 1:
            x = 0.5 * x + 25 * x / (1 + x ** 2) + 8 * np.cos(1.2 * (k - 1)) + rng.normal(0, math.sqrt(10), n)
        lw = -0.5 * (z[k - 1, 0] - x ** 2 / 20) ** 2
        w = np.exp(lw - lw.max())
        w /= w.sum()
        means.append(w @ x)
        x = x[rng.choice(n, n, p=w)]
    return np.array(means)


def test_rmse_matches_an_independent_bootstrap_filter():
    model = models.get("ungm")
    ours, reference = [], []
    for seed in range(20):
        truth, z = model.simulate(100, np.random.default_rng(1000 + seed))
        pf = ParticleFilter(model, z, 500, resampler="multinomial", seed=seed)
        means = np.array([step.mean[0] for step in pf])
        ours.append(np.sqrt(np.mean((means - truth[:, 0]) ** 2)))
        ref = bootstrap_reference(z, 500, seed, model)
        reference.append(np.sqrt(np.mean((ref - truth[:, 0]) ** 2)))
    difference = np.array(ours) - np.array(reference)
    # Paired over the same 20 data sets: the mean difference is within 4 standard errors of 0.
    standard_error = difference.std(ddof=1) / math.sqrt(len(difference))
    assert abs(difference.mean()) <= 4 * standard_error, (np.mean(ours), np.mean(reference))
    assert 2.0 < np.mean(ours) < 8.0


def test_same_seed_same_numbers_and_streams_are_per_step():
    model = models.get("ungm")
    _, z = model.simulate(30, np.random.default_rng(0))
    a = [s.mean for s in ParticleFilter(model, z, 200, seed=3)]
    b = [s.mean for s in ParticleFilter(model, z, 200, seed=3)]
    c = [s.mean for s in ParticleFilter(model, z, 200, seed=4)]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    first = ParticleFilter(model, z, 200, seed=3)
    step = next(first)
    expected = model.initial_particles(200, stream(3, "twin", 1, "entity"))
    np.testing.assert_array_equal(step.particles, expected)


@pytest.mark.parametrize("name", ["ungm", "ungm-printed", "video"])
def test_propagation_noise_drawn_ahead_gives_the_same_particles_and_stream(name):
    model = models.get(name)
    particles = model.initial_particles(50, np.random.default_rng(0))
    inside, ahead = stream(1, "t", 2, "entity"), stream(1, "t", 2, "entity")
    expected = model.propagate(particles, 2, inside)
    noise = model.propagation_noise(50, 2, ahead)
    assert noise is not None
    np.testing.assert_array_equal(model.propagate(particles, 2, ahead, noise=noise), expected)
    # What is drawn next (the resampling) comes out the same too.
    np.testing.assert_array_equal(inside.random(5), ahead.random(5))


class Undrawable(models.GrowthModel):
    """A model that draws only inside propagate (propagation_noise is the base class's None)."""

    def propagation_noise(self, n, k, rng):
        return None

    def propagate(self, particles, k, rng, noise=None):
        assert noise is None, "a model without propagation_noise must not be handed noise"
        return self.transition_mean(particles, k) + math.sqrt(self.process_var) * rng.standard_normal(particles.shape)


def keep(step, particles, weights, observation, parents):
    return Preprocessed(particles + 0.5, weights)  # moves the particles, keeps the very weights


def keep_a_copy(step, particles, weights, observation, parents):
    return Preprocessed(particles + 0.5, weights.copy())  # equal weights, another array


def reweigh(step, particles, weights, observation, parents):
    w = weights * (1.0 + np.arange(weights.size) % 3)  # other weights: what was resampled ahead is void
    return Preprocessed(particles, w / w.sum())


def skip_odd(step, particles, weights, observation, parents):
    return None if step % 2 else Preprocessed(particles, weights)  # degraded steps resample the own weights


@pytest.mark.parametrize("resampler", ["systematic", "multinomial", "stratified", "residual"])
@pytest.mark.parametrize("answer", [keep, keep_a_copy, reweigh, skip_odd])
@pytest.mark.parametrize("model", [models.get("ungm"), Undrawable()], ids=["ungm", "no-propagation-noise"])
def test_working_ahead_during_the_preprocessor_call_changes_no_number(model, answer, resampler):
    # As the entity service does: while the twin works, resample with the own weights and draw the next
    # step's noise.
    _, z = models.get("ungm").simulate(12, np.random.default_rng(0))
    plain = list(ParticleFilter(model, z, 300, seed=5, resampler=resampler, preprocessor=answer))
    calls = []

    def working(step, particles, weights, observation, parents):
        pf.work_ahead()
        pf.work_ahead()  # twice is once
        calls.append(step)
        return answer(step, particles, weights, observation, parents)

    pf = ParticleFilter(model, z, 300, seed=5, resampler=resampler, preprocessor=working)
    ahead = list(pf)
    assert calls == list(range(1, 13))
    assert pf._ahead is None and pf._resampled is None  # nothing left over past the last step
    for a, b in zip(plain, ahead):
        np.testing.assert_array_equal(a.particles, b.particles)
        np.testing.assert_array_equal(a.ancestors, b.ancestors)
        np.testing.assert_array_equal(a.mean, b.mean)


@pytest.mark.parametrize("answer", [keep, reweigh, skip_odd])
@pytest.mark.parametrize("resample_below", [None, 0.5])
def test_a_step_begun_and_finished_by_its_caller_gives_the_numbers_of_next(answer, resample_below):
    # The entity service's event loop asks the twin itself: begin_step, the question, work_ahead while the
    # answer is awaited, finish_step. With resample_below some steps are not due and ask nothing.
    _, z = models.get("ungm").simulate(15, np.random.default_rng(3))
    plain = list(ParticleFilter(models.get("ungm"), z, 300, seed=9, resample_below=resample_below,
                                preprocessor=answer))
    pf = ParticleFilter(models.get("ungm"), z, 300, seed=9, resample_below=resample_below)
    asked = []
    for k in range(15):
        pending = pf.begin_step(z[k])
        reply = None
        if pending.asks:
            asked.append(pending.step)
            pf.work_ahead()
            reply = answer(pending.step, pending.particles, pending.weights, pending.observation, pending.parents)
        step = pf.finish_step(pending, reply)
        a = plain[k]
        assert (step.step, step.resampled, step.degraded, step.parents) == (a.step, a.resampled, a.degraded,
                                                                             a.parents)
        np.testing.assert_array_equal(step.particles, a.particles)
        np.testing.assert_array_equal(step.mean, a.mean)
        if a.resampled:
            np.testing.assert_array_equal(step.ancestors, a.ancestors)
    assert asked == [s.step for s in plain if s.resampled]
    assert 0 < len(asked) and (resample_below is None) == (len(asked) == 15)


def test_resampling_ahead_outside_a_preprocessor_call_does_nothing():
    model = models.get("ungm")
    _, z = model.simulate(3, np.random.default_rng(0))
    pf = ParticleFilter(model, z, 100, seed=1)
    pf.resample_ahead()
    next(pf)
    pf.resample_ahead()
    assert pf._resampled is None


def test_a_step_prepared_but_skipped_is_not_used_for_another_step():
    model = models.get("ungm")
    _, z = model.simulate(5, np.random.default_rng(0))
    plain = [s.mean for s in ParticleFilter(model, z, 200, seed=2)]
    pf = ParticleFilter(model, z, 200, seed=2)
    next(pf)
    pf.prepare_next_step()       # drawn for step 2
    pf._ahead = (7, *pf._ahead[1:])  # pretend it was drawn for another step
    rest = [s.mean for s in pf]
    np.testing.assert_array_equal(rest, plain[1:])


def test_log_weights_survive_an_outlier_at_large_n():
    model = models.get("ungm")
    z = np.array([[0.5], [1e4], [2.0]])  # an observation no particle explains: log-likelihoods near -5e7
    pf = ParticleFilter(model, z, 1_000_000, seed=0)
    for step in pf:
        assert np.isfinite(step.weights).all()
        assert step.weights.sum() == pytest.approx(1.0)
        assert 1.0 <= step.ess <= 1_000_000


def test_every_step_reports_moments_and_interval():
    model = models.get("ungm")
    _, z = model.simulate(10, np.random.default_rng(0))
    for step in ParticleFilter(model, z, 300, seed=0):
        np.testing.assert_allclose(step.mean, step.weights @ step.particles)
        assert np.all(step.lower <= step.mean) and np.all(step.mean <= step.upper)
        np.testing.assert_allclose(step.upper - step.mean, 1.959963984540054 * np.sqrt(step.var))


def test_parents_count_the_distinct_ancestors_of_the_last_resampling():
    model = models.get("ungm")
    _, z = model.simulate(8, np.random.default_rng(0))
    steps = list(ParticleFilter(model, z, 400, seed=2))
    assert steps[0].parents is None
    for before, after in zip(steps, steps[1:]):
        assert after.parents == np.unique(before.ancestors).size < 400


def test_resample_below_skips_resampling_when_ess_is_high():
    model = models.get("ungm")
    _, z = model.simulate(50, np.random.default_rng(0))
    steps = list(ParticleFilter(model, z, 300, seed=0, resample_below=0.5))
    assert all(s.resampled == (s.ess < 150) for s in steps)
    assert 0 < sum(s.resampled for s in steps) < 50


def test_missing_preprocessor_answer_degrades_the_step_and_resamples_plainly():
    model = models.get("ungm")
    _, z = model.simulate(6, np.random.default_rng(0))

    def flaky(step, particles, weights, observation, parents):
        return None if step % 2 else Preprocessed(particles, weights, "ok")

    steps = list(ParticleFilter(model, z, 100, seed=1, preprocessor=flaky))
    assert [s.degraded for s in steps] == [True, False] * 3
    assert all(s.resampled for s in steps)
    plain = list(ParticleFilter(model, z, 100, seed=1))
    np.testing.assert_array_equal([s.mean for s in steps], [s.mean for s in plain])


def test_filter_rejects_bad_configuration():
    model = models.get("ungm")
    with pytest.raises(ValueError, match="unknown resampler 'best'"):
        ParticleFilter(model, np.zeros(3), 10, resampler="best")
    with pytest.raises(ValueError, match="n_particles must be at least 1"):
        ParticleFilter(model, np.zeros(3), 0)
    with pytest.raises(ValueError, match="observations contain non-finite values"):
        ParticleFilter(model, np.array([1.0, np.nan]), 10)


def test_filter_error_when_every_weight_is_zero():
    class Impossible(models.GrowthModel):
        def log_likelihood(self, particles, observation, k):
            return np.full(particles.shape[0], -np.inf)

    with pytest.raises(FilterError, match="no particle explains the observation"):
        next(ParticleFilter(Impossible(), np.zeros(2), 10))


# --- in-process pipeline ----------------------------------------------------------------

def test_inprocess_pipeline_is_deterministic_and_runs_every_layer():
    config = RunConfig(particles=300, steps=40, seed=5)
    a, b = inprocess.run(config), inprocess.run(config)
    np.testing.assert_array_equal(a.means, b.means)
    assert len(a.steps) == 40 and a.resamplings == 40 and a.degraded == 0
    assert all(s.report is not None and s.report.ps == 0.81 for s in a.steps)
    plain = inprocess.run(config.model_copy(update={"preprocess": False}))
    np.testing.assert_array_equal(plain.truth, a.truth)  # same scenario stream
    assert not np.array_equal(plain.means, a.means)      # preprocessing changed the estimates


def test_run_config_fails_at_construction():
    with pytest.raises(ValueError, match="unknown resampler 'fast'"):
        RunConfig(resampler="fast")
    with pytest.raises(ValueError, match="unknown scenario 'lorenz'; expected one of drift, moving, switching, ungm, ungm-printed, video"):
        RunConfig(scenario="lorenz")
    with pytest.raises(ValueError, match="less than or equal to 1"):
        RunConfig(ps=1.2)
    with pytest.raises(ValueError, match="should match pattern"):
        RunConfig(twin="a/b")


def test_a_model_that_propagates_to_nan_fails_at_that_step():
    class Exploding(models.GrowthModel):
        def propagate(self, particles, k, rng, noise=None):
            out = super().propagate(particles, k, rng, noise)
            if k == 3:
                out[7, 0] = np.inf
            return out

    _, z = models.get("ungm").simulate(5, np.random.default_rng(0))
    pf = ParticleFilter(Exploding(), z, 50, seed=0)
    next(pf), next(pf)
    with pytest.raises(ValueError, match=r"particles contain non-finite values at index 7 \(value inf\)"):
        next(pf)


# --- no avoidable temporaries, the same numbers ---------------------------------------

@pytest.mark.parametrize("n", [100, 5000])  # numpy draws the noise below COMPILED_DRAWS, the kernel above
def test_growth_model_kernels_give_the_numbers_of_the_numpy_laws(n):
    # dtpf.entity._growth does Eq. 35 and 36 in compiled passes: bit for bit the numpy expressions.
    model = models.get("ungm")
    rng = np.random.default_rng(3)
    x = 10.0 * rng.standard_normal((n, 1))
    x[:3, 0] = [0.0, -0.0, 1e70]
    for k in (1, 2, 17):
        noise = np.random.default_rng(k).standard_normal((n, 1))
        expected = noise * math.sqrt(model.process_var) + model.transition_mean(x, k)
        np.testing.assert_array_equal(model.propagate(x, k, np.random.default_rng(k)), expected)
        np.testing.assert_array_equal(model.propagate(x, k, None, noise=noise.copy()), expected)
        np.testing.assert_array_equal(model.propagation_noise(n, k, np.random.default_rng(k)), noise)
        z = 3.0
        residual = z - x[:, 0] ** 2 / 20.0
        expected = -0.5 * residual * residual / model.observation_var - 0.5 * math.log(
            2.0 * math.pi * model.observation_var)
        np.testing.assert_array_equal(model.log_likelihood(x, np.array([z]), k), expected)


class InPlaceGrowth(models.GrowthModel):
    """A model whose propagate overwrites its input and returns it (allowed: it may work in place)."""

    def propagate(self, particles, k, rng, noise=None):
        particles[:] = super().propagate(particles, k, rng, noise)
        return particles


def copying(step, particles, weights, observation, parents):
    return Preprocessed(particles + 0.0, weights)


@pytest.mark.parametrize("preprocessor", [None, copying], ids=["plain", "preprocessed"])
@pytest.mark.parametrize("model", [models.get("ungm"), InPlaceGrowth()], ids=["ungm", "in-place"])
def test_steps_kept_after_the_run_keep_their_own_numbers(model, preprocessor):
    # The filter reuses the array it gathers the resampled set into; no step it returned may see it change.
    _, z = models.get("ungm").simulate(15, np.random.default_rng(2))
    copies = [(s.particles.copy(), s.weights.copy(), s.ancestors.copy())
              for s in ParticleFilter(model, z, 200, seed=4, preprocessor=preprocessor)]
    kept = list(ParticleFilter(model, z, 200, seed=4, preprocessor=preprocessor))
    for (particles, weights, ancestors), step in zip(copies, kept):
        np.testing.assert_array_equal(step.particles, particles)
        np.testing.assert_array_equal(step.weights, weights)
        np.testing.assert_array_equal(step.ancestors, ancestors)


def write_late_model(folder) -> None:
    """late.py:MODEL, the growth model whose propagate raises an IndexError at step 5 (at late.py line 7)."""
    (folder / "late.py").write_text(
        "from dtpf.entity.models import get\n\n\nclass Late(type(get('ungm'))):\n"
        "    def propagate(self, particles, k, rng, noise=None):\n"
        "        if k == 5:\n"
        "            return particles[[1, 2, 3]][10]\n"
        "        return super().propagate(particles, k, rng, noise=noise)\n\n\nMODEL = Late()\n")


def test_a_model_that_fails_mid_run_is_one_line_naming_the_step_the_method_and_its_line(tmp_path):
    """An IndexError in a model's propagate at step 5 stops the run with one line (exit 2 from the CLI), not a
    traceback."""
    import subprocess
    import sys

    write_late_model(tmp_path)
    from dtpf.entity import model_ref

    model = model_ref.resolve(f"{tmp_path / 'late.py'}:MODEL")
    truth, z = models.get("ungm").simulate(10, np.random.default_rng(0))
    pf = ParticleFilter(model, z, 50, seed=1)
    with pytest.raises(FilterError, match=r"^step 5: the model's propagate raised IndexError: index 10 is out of "
                                          r"bounds for axis 0 with size 3 \(at late.py line 7\)$"):
        list(pf)
    done = subprocess.run([sys.executable, "-P", "-m", "dtpf", "run", "-q", "--policy", "fixed", "-T", "10", "--model",
                           "late.py:MODEL"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip() == ("dtpf run: error: step 5: the model's propagate raised IndexError: index 10 is "
                                   "out of bounds for axis 0 with size 3 (at late.py line 7)")


def test_a_model_that_fails_mid_run_under_launch_ends_with_its_line_and_the_summary_says_the_run_failed(tmp_path):
    """Under dtpf launch the same model ends the launch with the entity's one line (exit 1: the run started
    and failed; 2 is for what is refused before it starts) and the summary of its log says the run failed at
    step 5 rather than 'complete'."""
    import subprocess
    import sys

    write_late_model(tmp_path)
    said = ("step 5: the model's propagate raised IndexError: index 10 is out of bounds for axis 0 with size 3 "
            "(at late.py line 7)")
    done = subprocess.run([sys.executable, "-P", "-m", "dtpf", "launch", "-T", "10", "-n", "200", "--model",
                           "late.py:MODEL", "-o", "run.mcap"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines()[-1] == f"dtpf launch: error: {said}", done.stderr
    summary = subprocess.run([sys.executable, "-P", "-m", "dtpf", "summary", "run.mcap"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
    lines = summary.stdout.splitlines()
    assert lines[1] == "state         run failed at step 5: " + said.removeprefix("step 5: "), summary.stdout
    assert lines[2] == "              (the file: complete)", summary.stdout
