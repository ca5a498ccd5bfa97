"""Model references (dtpf.entity.model_ref) and the startup probe (dtpf.entity.model_check)."""
from __future__ import annotations

import pickle
import sys
import textwrap
import time

import numpy as np
import pytest

from dtpf.entity import model_check, model_ref, models
from dtpf.entity.filter import ParticleFilter
from dtpf.entity.model_check import check_model, load_checked
from dtpf.entity.model_ref import ModelError, is_reference, registered_names, resolve

from conftest import ROOT

EXAMPLE = ROOT / "docs" / "examples" / "range_bearing.py"

#: A small valid model: a 2-D random walk observed in its first coordinate.
WALK = """
from dataclasses import dataclass
import numpy as np
from dtpf.entity.models import StateSpaceModel

@dataclass(frozen=True)
class Walk(StateSpaceModel):
    name: str = "walk"
    dim: int = 2
    obs_dim: int = 1

    def initial_particles(self, n, rng):
        return rng.standard_normal((n, 2))

    def propagate(self, particles, k, rng, noise=None):
        return particles + rng.standard_normal(particles.shape)

    def log_likelihood(self, particles, observation, k):
        return -0.5 * (particles[:, 0] - np.asarray(observation).reshape(-1)[0]) ** 2

    def sample_observation(self, states, k, rng):
        return states[:, :1] + rng.standard_normal((states.shape[0], 1))
"""


@pytest.fixture(autouse=True)
def fresh_caches(monkeypatch):
    """Each test resolves and checks from scratch."""
    monkeypatch.setattr(model_ref, "_CACHE", {})
    monkeypatch.setattr(model_check, "_CHECKED", {})


@pytest.fixture
def write(tmp_path):
    """Write a model file into tmp_path: write(source, name="m.py") -> path."""
    def _write(source: str, name: str = "m.py"):
        path = tmp_path / name
        path.write_text(textwrap.dedent(source))
        return path
    return _write


def model_file(write, extra: str = "", name: str = "m.py"):
    return write(WALK + textwrap.dedent(extra), name)


def raises(ref: str, match: str) -> str:
    """Resolve ``ref``, expect a one-line ModelError matching ``match``; return the message."""
    with pytest.raises(ModelError, match=match) as info:
        resolve(ref)
    message = str(info.value)
    assert "\n" not in message
    return message


def check_raises(model, match: str, **kwargs) -> str:
    with pytest.raises(ModelError, match=match) as info:
        check_model(model, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    return message


# --- the four forms ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["ungm", "ungm-printed"])
def test_builtin_name_is_the_registered_object(name):
    assert resolve(name) is models.get(name)
    assert not is_reference(name)


def test_file_reference_to_an_instance_a_subclass_and_a_factory(write):
    path = model_file(write, """
        INSTANCE = Walk(name="instance")
        def make():
            return Walk(name="factory")
    """)
    instance = resolve(f"{path}:INSTANCE")
    subclass = resolve(f"{path}:Walk")
    factory = resolve(f"{path}:make")
    assert (instance.name, subclass.name, factory.name) == ("instance", "walk", "factory")
    assert type(instance) is type(subclass) is type(factory)  # the file was imported once
    assert instance is resolve(f"{path}:INSTANCE")  # cached per reference
    assert is_reference(f"{path}:Walk")


def test_file_reference_relative_to_the_current_directory(write, tmp_path, monkeypatch):
    model_file(write, name="rel.py")
    monkeypatch.chdir(tmp_path)
    model = resolve("rel.py:Walk")
    assert model.dim == 2
    # The module is registered under a stable name, so the model pickles.
    assert pickle.loads(pickle.dumps(model)) == model
    assert type(model).__module__ in sys.modules


def test_module_reference(write, tmp_path, monkeypatch):
    model_file(write, "MODEL = Walk(name='from-module')\n", name="dtpf_test_walk_module.py")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "dtpf_test_walk_module", raising=False)
    try:
        model = resolve("dtpf_test_walk_module:MODEL")
        assert model.name == "from-module"
        assert model is sys.modules["dtpf_test_walk_module"].MODEL
    finally:
        sys.modules.pop("dtpf_test_walk_module", None)


def test_example_resolves_and_passes_the_check():
    ref = f"{EXAMPLE}:RangeBearingTarget"
    model = resolve(ref)
    assert (model.name, model.dim, model.obs_dim) == ("range-bearing", 4, 2)
    check_model(model, ref=ref)
    assert load_checked(ref) is model


def test_example_relative_to_the_repo_root(monkeypatch):
    monkeypatch.chdir(ROOT)
    model = resolve("docs/examples/range_bearing.py:RangeBearingTarget")
    assert model.name == "range-bearing"


def test_example_noise_drawn_ahead_gives_the_same_particles():
    model = resolve(f"{EXAMPLE}:RangeBearingTarget")
    x = model.initial_particles(50, np.random.default_rng(0))
    plain = model.propagate(x.copy(), 2, np.random.default_rng(1))
    rng = np.random.default_rng(1)
    ahead = model.propagate(x.copy(), 2, rng, noise=model.propagation_noise(50, 2, rng))
    np.testing.assert_array_equal(plain, ahead)


def test_example_csv_is_what_the_script_writes(tmp_path):
    sys.path.insert(0, str(EXAMPLE.parent))
    try:
        import make_range_bearing_csv
    finally:
        sys.path.remove(str(EXAMPLE.parent))
    full, bare = make_range_bearing_csv.main(tmp_path)
    # numpy's arctan2 picks its SIMD loop by CPU: the bearings may differ in the last bit from one machine
    # to another (seen: 5 of 101 rows, 1 ulp), so the numbers are compared to 1e-13, the text's shape exactly.
    for made, kept in ((full, "range_bearing.csv"), (bare, "range_bearing_no_truth.csv")):
        made_lines, kept_lines = made.read_text().splitlines(), (EXAMPLE.parent / kept).read_text().splitlines()
        assert made_lines[0] == kept_lines[0] and len(made_lines) == len(kept_lines)
        made_values = np.array([[float(v) for v in line.split(",")] for line in made_lines[1:]])
        kept_values = np.array([[float(v) for v in line.split(",")] for line in kept_lines[1:]])
        np.testing.assert_allclose(made_values, kept_values, rtol=1e-13, atol=0)
    header = full.read_text().splitlines()[0]
    assert header == "time,range,bearing,truth_x,truth_y,truth_vx,truth_vy"


def test_bootstrap_filter_tracks_the_example():
    model = resolve(f"{EXAMPLE}:RangeBearingTarget")
    data = np.loadtxt(EXAMPLE.parent / "range_bearing.csv", delimiter=",", skiprows=1)
    z, truth = data[:, 1:3], data[:, 3:7]
    means = np.array([step.mean for step in ParticleFilter(model, z, 2000, seed=1)])
    rmse = np.sqrt(np.mean(np.sum((means[:, :2] - truth[:, :2]) ** 2, axis=1)))
    # Inverting each observation alone gives about 2.3 here; the filter measured 1.44.
    assert rmse < 2.0


# --- entry points -----------------------------------------------------------------------------------------

@pytest.fixture
def installed(tmp_path, monkeypatch):
    """A fake installed distribution on sys.path registering models in dtpf.models."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "dtpf_fake_models.py").write_text(textwrap.dedent(WALK) + "RADAR = Walk(name='radar')\n")
    info = site / "dtpf_fake-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: dtpf-fake\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[dtpf.models]\n"
        "fake-radar = dtpf_fake_models:RADAR\n"
        "fake-walk = dtpf_fake_models:Walk\n"
        "ungm = dtpf_fake_models:RADAR\n"
        "fake-broken = dtpf_fake_models:MISSING\n"
        "fake-gone = dtpf_fake_gone:M\n"
    )
    monkeypatch.syspath_prepend(str(site))
    yield site
    sys.modules.pop("dtpf_fake_models", None)


def test_entry_point_names_resolve(installed):
    names = registered_names()
    assert names == sorted(set(names))
    assert {"ungm", "ungm-printed", "video", "fake-radar", "fake-walk"} <= set(names)
    radar = resolve("fake-radar")
    assert radar.name == "radar" and radar is sys.modules["dtpf_fake_models"].RADAR
    assert resolve("fake-walk").name == "walk"


def test_entry_point_does_not_override_a_builtin(installed):
    assert registered_names().count("ungm") == 1
    assert resolve("ungm") is models.get("ungm")


def test_entry_point_errors_name_the_entry_point(installed):
    message = raises("fake-broken", r"has no attribute 'MISSING'; it defines: RADAR, Walk")
    assert "entry point 'dtpf_fake_models:MISSING'" in message and "dtpf-fake" in message
    raises("fake-gone", r"cannot import module 'dtpf_fake_gone' .*No module named 'dtpf_fake_gone'")


def test_unknown_name_lists_builtin_and_entry_point_names(installed):
    message = raises("nope", r"unknown model 'nope'; built-in: ungm, ungm-printed, video, drift, switching, moving;")
    assert "fake-radar" in message and "fake-walk" in message


# --- resolve errors ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("ref", ["", "   "])
def test_empty_reference(ref):
    raises(ref, r"model reference is empty")


def test_unknown_plain_name():
    message = raises("nope", r"unknown model 'nope'; built-in: ungm, ungm-printed, video, drift, switching, moving; "
                             r"registered under dtpf.models")
    assert "package.module:NAME" in message


def test_file_path_without_name():
    raises("my_model.py", r"to load a model from a file, name it: my_model.py:NAME")


def test_module_not_importable():
    raises("dtpf_no_such_pkg.sub:M", r"cannot import module 'dtpf_no_such_pkg.sub' of model reference "
                                     r"'dtpf_no_such_pkg.sub:M': No module named 'dtpf_no_such_pkg' "
                                     r"\(is the package installed\? pip install dtpf_no_such_pkg")


def test_submodule_not_found():
    raises("entity.no_such_module:M", r"cannot import module 'entity.no_such_module' .*"
                                      r"No module named 'entity.no_such_module'")


def test_not_a_module_name():
    raises("not a module:M", r"'not a module' is neither a module name")


def test_file_not_found(tmp_path):
    missing = tmp_path / "nowhere" / "m.py"
    raises(f"{missing}:M", rf"model file '{missing}' not found")


def test_file_raises_while_imported(write):
    path = write("import math\nX = 1\nraise RuntimeError('bad config\\nsecond line')\n")
    message = raises(f"{path}:X", r"importing .*m\.py raised RuntimeError: bad config \(at m\.py line 3\)$")
    assert "second line" not in message


def test_file_with_syntax_error(write):
    path = write("def broken(:\n")
    raises(f"{path}:X", r"raised SyntaxError: invalid syntax \(m\.py, line 1\)$")
    assert not [m for m in list(sys.modules.values()) if getattr(m, "__file__", None) == str(path)]


def test_file_importing_a_missing_package(write):
    path = write("import dtpf_absent_dependency\n")
    raises(f"{path}:X", r"raised ModuleNotFoundError: No module named 'dtpf_absent_dependency'.*"
                        r"pip install dtpf_absent_dependency")


def test_attribute_missing_lists_models(write):
    path = model_file(write, "INSTANCE = Walk()\n_HIDDEN = Walk()\n")
    message = raises(f"{path}:Wlak", r"has no attribute 'Wlak'; it defines: INSTANCE, Walk$")
    assert "_HIDDEN" not in message


def test_attribute_missing_in_a_file_without_models(write):
    path = write("X = 1\n")
    raises(f"{path}:M", r"has no attribute 'M'; it defines no StateSpaceModel instance or subclass")


def test_nothing_after_the_colon(write):
    path = model_file(write)
    raises(f"{path}:", r"nothing after ':'")


@pytest.mark.parametrize("source, match", [
    ("X = 3\n", r"X is an int, expected a StateSpaceModel instance, subclass or zero-argument factory"),
    ("X = 'walk'\n", r"X is a str, expected"),
    ("class X:\n    pass\n", r"X is a class that does not derive from StateSpaceModel"),
    ("def X():\n    return 42\n", r"X\(\) returned an int, expected a StateSpaceModel instance"),
])
def test_not_a_model(write, source, match):
    path = write(source)
    raises(f"{path}:X", match)


def test_abstract_class_names_the_missing_methods(write):
    path = model_file(write, """
        class Half(StateSpaceModel):
            dim = 1
            obs_dim = 1
            def initial_particles(self, n, rng):
                return np.zeros((n, 1))
            def propagate(self, particles, k, rng, noise=None):
                return particles
    """)
    raises(f"{path}:Half", r"Half cannot be instantiated: it does not implement the abstract method "
                           r"log_likelihood$")


def test_factory_raising(write):
    path = model_file(write, """
        def make():
            raise ValueError("no calibration file")
    """)
    raises(f"{path}:make", r"make\(\) raised ValueError: no calibration file \(at m\.py line \d+\)")


def test_constructor_raising(write):
    path = model_file(write, """
        class Bad(Walk):
            def __init__(self):
                raise KeyError("sensor")
    """)
    raises(f"{path}:Bad", r"Bad\(\) raised KeyError: 'sensor'")


@pytest.mark.parametrize("source, match", [
    ("def X(scale):\n    pass\n", r"X\(\) needs arguments \(missing a required argument: 'scale'\)"),
    ("class X(Walk):\n    def __init__(self, gain):\n        pass\n",
     r"X\(\) needs arguments \(missing a required argument: 'gain'\)"),
])
def test_factory_or_class_needing_arguments(write, source, match):
    path = model_file(write, source)
    raises(f"{path}:X", match)


@pytest.mark.parametrize("attribute, value", [("dim", 0), ("obs_dim", -1), ("dim", 2.0), ("dim", True),
                                              ("obs_dim", "1")])
def test_bad_dimensions(write, attribute, value):
    path = model_file(write, f"BAD = Walk(**{{{attribute!r}: {value!r}}})\n")
    raises(f"{path}:BAD", rf"{attribute} is {value!r}, expected a positive int")


def test_missing_dimension(write):
    path = model_file(write, """
        class NoDim(StateSpaceModel):
            obs_dim = 1
            initial_particles = Walk.initial_particles
            propagate = Walk.propagate
            log_likelihood = Walk.log_likelihood
    """)
    raises(f"{path}:NoDim", r"the model has no attribute dim, expected a positive int")


def test_nameless_model_gets_the_reference_as_its_name(write):
    path = model_file(write, """
        class Plain(StateSpaceModel):
            dim = 2
            obs_dim = 1
            initial_particles = Walk.initial_particles
            propagate = Walk.propagate
            log_likelihood = Walk.log_likelihood
        class Slotted(Plain):
            __slots__ = ()
            @property
            def name(self):
                return 7
    """)
    ref = f"{path}:Plain"
    assert resolve(ref).name == ref
    assert resolve(f"{path}:Slotted").name == 7  # a read-only name is left alone


def test_reference_must_be_a_string():
    with pytest.raises(ModelError, match=r"model reference must be a string, got None"):
        resolve(None)


# --- check_model ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["ungm", "ungm-printed"])
def test_builtin_models_pass(name):
    check_model(models.get(name), ref=name)
    check_model(models.get(name), observation=[3.0], needs_sampling=True)


def test_video_model_passes_quickly():
    model = models.get("video")
    start = time.perf_counter()
    check_model(model, ref="video")
    assert time.perf_counter() - start < 5.0
    check_raises(model, r"model 'video': sample_observation is not implemented, but policy 'predictive' needs it",
                 needs_sampling="policy 'predictive'")


def broken_walk(write, methods: str, name: str = "m.py"):
    """A Walk subclass ``Broken`` overriding ``methods``, resolved (resolve itself does not probe)."""
    body = textwrap.indent(textwrap.dedent(methods), "    ") if methods.strip() else "    pass\n"
    path = model_file(write, "class Broken(Walk):\n" + body, name)
    return resolve(f"{path}:Broken"), f"{path}:Broken"


def test_wrong_propagate_shape(write):
    model, ref = broken_walk(write, """
        def propagate(self, particles, k, rng, noise=None):
            return particles[:, :1]
    """)
    message = check_raises(model, r"propagate returned shape \(5, 1\), expected \(5, 2\) "
                                  r"\(N particles by dim 2\)$", ref=ref)
    assert message.startswith(f"model 'walk' (ref {ref}): ")


def test_nan_likelihood(write):
    model, _ = broken_walk(write, """
        def log_likelihood(self, particles, observation, k):
            out = np.zeros(particles.shape[0])
            out[2] = np.nan
            return out
    """)
    check_raises(model, r"model 'walk': log_likelihood returned NaN at index 2")


def test_positive_infinite_likelihood(write):
    model, _ = broken_walk(write, """
        def log_likelihood(self, particles, observation, k):
            out = np.zeros(particles.shape[0])
            out[4] = np.inf
            return out
    """)
    check_raises(model, r"log_likelihood returned \+inf at index 4")


def test_likelihood_minus_inf_everywhere(write):
    model, _ = broken_walk(write, """
        def log_likelihood(self, particles, observation, k):
            return np.where(np.abs(particles[:, 0] - observation[0]) < 1e-9, 0.0, -np.inf)
    """)
    check_raises(model, r"log_likelihood is -inf for every probe particle: no particle explains the first "
                        r"observation", observation=[1e6])


def test_likelihood_disagreeing_with_sampling(write):
    model, _ = broken_walk(write, """
        def log_likelihood(self, particles, observation, k):
            out = np.zeros(particles.shape[0])
            out[0] = -np.inf
            return out
    """)
    check_raises(model, r"-inf for the probe particle its observation was sampled from")


def test_likelihood_wrong_shape(write):
    model, _ = broken_walk(write, """
        def log_likelihood(self, particles, observation, k):
            return np.zeros((particles.shape[0], 1))
    """)
    check_raises(model, r"log_likelihood returned shape \(5, 1\), expected \(5,\) \(one per particle\)")


def test_object_dtype(write):
    model, _ = broken_walk(write, """
        def initial_particles(self, n, rng):
            return np.array([[object(), object()]] * n)
    """)
    check_raises(model, r"initial_particles returned dtype object, expected float64-convertible numbers$")


def test_non_finite_particles(write):
    model, _ = broken_walk(write, """
        def propagate(self, particles, k, rng, noise=None):
            out = particles.copy()
            out[3, 1] = -np.inf
            return out
    """)
    check_raises(model, r"propagate returned -inf at index \(3, 1\), expected finite numbers")


def test_raising_method(write):
    model, _ = broken_walk(write, """
        def propagate(self, particles, k, rng, noise=None):
            return particles + self.velocity
    """)
    check_raises(model, r"propagate raised AttributeError: 'Broken' object has no attribute 'velocity'$")


def test_raising_method_multiline_message(write):
    model, _ = broken_walk(write, """
        def initial_particles(self, n, rng):
            raise TypeError("first line\\nsecond line")
    """)
    message = check_raises(model, r"initial_particles raised TypeError: first line$")
    assert "second" not in message


def test_needs_sampling_without_sample_observation(write):
    path = model_file(write, """
        class Blind(StateSpaceModel):
            name = "blind"
            dim = 2
            obs_dim = 1
            initial_particles = Walk.initial_particles
            propagate = Walk.propagate
            log_likelihood = Walk.log_likelihood
    """)
    model = resolve(f"{path}:Blind")
    assert not model.samples_observations
    check_model(model)  # nothing to sample from, no observation: the likelihood is not probed
    check_model(model, observation=[0.5])
    check_raises(model, r"model 'blind': sample_observation is not implemented, but dtpf sensor needs it$",
                 needs_sampling="dtpf sensor")
    check_raises(model, r"sample_observation is not implemented, but this run", needs_sampling=True)


def test_sample_observation_wrong_shape(write):
    model, _ = broken_walk(write, """
        def sample_observation(self, states, k, rng):
            return states
    """)
    check_raises(model, r"sample_observation returned shape \(5, 2\), expected \(5, 1\) \(N states by obs_dim 1\)")


def test_observation_of_the_wrong_size(write):
    model, _ = broken_walk(write, "")
    check_raises(model, r"observation has 3 values, model observes 1$", observation=[1.0, 2.0, 3.0])


def test_noise_drawn_ahead_must_match(write):
    model, _ = broken_walk(write, """
        def propagation_noise(self, n, k, rng):
            return rng.standard_normal((n, 2))
        def propagate(self, particles, k, rng, noise=None):
            if noise is None:
                noise = 2.0 * rng.standard_normal(particles.shape)
            return particles + noise
    """)
    check_raises(model, r"propagate\(noise=propagation_noise\(...\)\) gives other particles")


def test_propagation_noise_not_an_array(write):
    model, _ = broken_walk(write, """
        def propagation_noise(self, n, k, rng):
            return [0.0] * n
    """)
    check_raises(model, r"propagation_noise returned a list, expected None or an array")


@pytest.mark.parametrize("moments, match", [
    ("(particles[:, :1], np.array([-1.0]))", r"observation_moments variances are negative at index 0"),
    ("(particles, np.array([1.0]))", r"observation_moments means returned shape \(5, 2\), expected \(5, 1\)"),
    ("(particles[:, :1], np.array([np.nan]))", r"observation_moments variances returned NaN at index 0"),
    ("particles[:, :1]", r"observation_moments returned an ndarray, expected None or a pair"),
])
def test_bad_observation_moments(write, moments, match):
    model, _ = broken_walk(write, f"""
        def observation_moments(self, particles, k):
            return {moments}
    """)
    check_raises(model, match)


def test_not_a_model_at_all():
    check_raises(object(), r"object is not a StateSpaceModel")


def test_bad_dimension_in_check(write):
    model, _ = broken_walk(write, "")
    object.__setattr__(model, "obs_dim", 0)
    check_raises(model, r"model 'walk': obs_dim is 0, expected a positive int")


# --- load_checked -----------------------------------------------------------------------------------------

def test_load_checked_probes_once_per_reference(write, monkeypatch):
    path = model_file(write)
    ref = f"{path}:Walk"
    calls = []
    monkeypatch.setattr(model_check, "check_model", lambda model, **kw: calls.append(kw["needs_sampling"]))
    first = load_checked(ref)
    assert load_checked(ref) is first is resolve(ref)
    load_checked(ref, needs_sampling="dtpf sensor")
    load_checked(ref, needs_sampling="dtpf sensor")
    assert calls == [False, "dtpf sensor"]


def test_load_checked_raises_and_does_not_cache_a_failure(write):
    model, ref = broken_walk(write, """
        def propagate(self, particles, k, rng, noise=None):
            return particles[:, :1]
    """)
    for _ in range(2):
        with pytest.raises(ModelError, match=r"propagate returned shape"):
            load_checked(ref)


def test_a_users_model_names_its_twin_unless_a_twin_is_given():
    from dtpf.messages.config import RunConfig, twin_of_model

    assert twin_of_model("models/rover.py:Rover") == "rover-1"
    assert twin_of_model("lab.models:Rover") == "models-1"
    assert twin_of_model("../my model.py:M") == "my-model-1"
    assert RunConfig(model="models/rover.py:Rover", steps=5).twin == "rover-1"
    assert RunConfig(model="models/rover.py:Rover", steps=5, twin="arm-7").twin == "arm-7"
    assert RunConfig(steps=5).twin == "ungm-1"  # a built-in scenario keeps its twin
