"""Your own model, named by ``env.model._target_`` or handed over as ``escort_rl.train(..., model=obj)``,
is refused with one line naming the config key, the attribute or the method when it does not fit, and
before anything trains or is written: a target whose module fails to import (and why), a target that is
not a class, constructor arguments that do not fit, a constructor that fails inside torch, and the
protocol's mistakes the probe catches beyond ``test_probe.py``'s (non-finite or mistyped outputs, a
Cholesky factor that is not one, a detached transition density, no actions); ``model=`` with keys that
would never reach the object, or an object that cannot be saved with its run."""

from __future__ import annotations

import pytest
import torch
from test_probe import Drift

import escort_rl
from conftest import config_error, tiny_overrides
from conftest import one_line_error as one_error_line
from escort_rl.config import ConfigError, compose
from escort_rl.trainers.builders import build_model

HERE = __name__


def one_line_error(fn) -> str:
    """The one-line message of the ``ConfigError`` that ``fn()`` raises."""
    return one_error_line(fn, ConfigError)


def built(*overrides: str):
    return build_model(compose(["env=custom", *overrides]).env)


# ---------------------------------------------------------------------------------------------
# env.model._target_
# ---------------------------------------------------------------------------------------------

MODULES = {
    "body_fails": "import torch\nraise RuntimeError('calibration file missing')\n",
    "syntax_error": "class Model(:\n    pass\n",
    "missing_dependency": "import no_such_dependency_of_the_model\n\nclass Model:\n    pass\n",
}


@pytest.mark.parametrize("module, reason", [
    ("body_fails", "(RuntimeError: calibration file missing)"),
    ("syntax_error", "(SyntaxError: "),
    ("missing_dependency", "(ModuleNotFoundError: No module named 'no_such_dependency_of_the_model')"),
], ids=sorted(MODULES))
def test_a_target_whose_module_fails_to_import_names_why(module, reason, tmp_path, monkeypatch):
    """It used to be a traceback from the module's body, or 'cannot import' without the reason (the
    missing dependency read as if the model's own module were missing)."""
    name = f"user_models_{module}"
    (tmp_path / f"{name}.py").write_text(MODULES[module])
    monkeypatch.syspath_prepend(str(tmp_path))
    message = one_line_error(lambda: built(f"env.model._target_={name}.Model"))
    assert message.startswith(f"env.model._target_: cannot import '{name}.Model' {reason}"), message


@pytest.mark.parametrize("target, kind", [("math.pi", "float"), ("escort_rl.models.probe", "module")],
                         ids=["a-number", "a-module"])
def test_a_target_that_is_not_a_class_is_named(target, kind):
    message = one_line_error(lambda: built(f"env.model._target_={target}"))
    assert message.startswith(f"env.model._target_: '{target}' is not a class or a function (Expected a callable "
                              f"target, got "), message
    assert f"of type '{kind}'); name a class, e.g. my_pkg.models.MyModel" in message


def returns_nothing():
    return None


class Noisy(Drift):
    def __init__(self, noise: float = 0.1) -> None:
        self.obs_noise = float(noise)


class CholeskyInConstructor(Drift):
    def __init__(self) -> None:
        self.tril = torch.linalg.cholesky(torch.tensor([[1.0, 2.0], [2.0, 1.0]]))  # not positive definite


@pytest.mark.parametrize("overrides, expected", [
    ([f"env.model._target_={HERE}.returns_nothing"],
     "env.model: model.state_dim: expected an int attribute on NoneType; a model must follow "
     "escort_rl.models.POMDPModel"),
    ([f"env.model._target_={HERE}.Noisy", "+env.model.nois=0.2"],
     "env.model: Noisy.__init__() got an unexpected keyword argument 'nois'"),
    (["env.model._target_=escort_rl.models.LinearGaussian", "+env.model.state_dim=-1"],
     "env.model: LinearGaussian.state_dim: must be >= 1, got -1"),
    ([f"env.model._target_={HERE}.CholeskyInConstructor"],
     f"env.model: building '{HERE}.CholeskyInConstructor' raised _LinAlgError: linalg.cholesky: The factorization "
     "could not be completed"),
], ids=["a-function-that-returns-none", "misspelt-keyword", "value-out-of-range", "torch-error-in-the-constructor"])
def test_a_target_that_cannot_be_built_is_named(overrides, expected):
    assert one_line_error(lambda: built(*overrides)).startswith(expected)


def test_a_keyword_without_its_plus_is_named_while_composing():
    assert config_error(["env=custom", f"env.model._target_={HERE}.Noisy", "env.model.noise=0.2"]) == (
        "config: unknown key 'env.model.noise'; check the spelling against `escort-rl config`, or add a new key on "
        "purpose with +key=value")


# ---------------------------------------------------------------------------------------------
# What the probe refuses (beyond test_probe.py)
# ---------------------------------------------------------------------------------------------


class NaNTransition(Drift):
    def transition(self, s, a, generator=None):
        return super().transition(s, a, generator) * float("nan")


class Float64Observation(Drift):
    def observe(self, s_next, a, generator=None):
        return super().observe(s_next, a, generator).double()


class IntegerObservation(Drift):
    def observe(self, s_next, a, generator=None):
        return super().observe(s_next, a, generator).round().long()


class UpperTriangularScale(Drift):
    def transition_scale_tril(self):
        return torch.tensor([[0.05, 0.01], [0.0, 0.02]])


class NegativeScale(Drift):
    def transition_scale_tril(self):
        return torch.diag(torch.tensor([0.05, -0.02]))


class DetachedTransitionDensity(Drift):
    def transition_log_prob(self, s_next, s, a):
        return super().transition_log_prob(s_next.detach(), s, a)


class InfiniteTransitionDensity(Drift):
    def transition_log_prob(self, s_next, s, a):
        return super().transition_log_prob(s_next, s, a) + float("inf")


class DistancePerCoordinate(Drift):
    def distance_to_goal(self, s):
        return s.abs()


class FloatStateDim(Drift):
    state_dim = 2.0


class NoActions(Drift):
    n_actions = 0


class NegativeActions(Drift):
    n_actions = -3


class BoolActions(Drift):
    n_actions = True


PROBED = [
    (NaNTransition, "model.transition(s, a, generator): expected finite values, got 6 of 6 that are not (e.g. nan)"),
    (Float64Observation, "model.observe(s_next, a, generator): expected dtype torch.float32, got torch.float64; the "
                         "policies and filters run in float32"),
    (IntegerObservation, "model.observe(s_next, a, generator): expected dtype torch.float32, got torch.int64"),
    (UpperTriangularScale, "model.transition_scale_tril(): expected a lower-triangular matrix with a diagonal >= 0"),
    (NegativeScale, "model.transition_scale_tril(): expected a lower-triangular matrix with a diagonal >= 0"),
    (DetachedTransitionDensity, "model.transition_log_prob(s_next, s, a): not differentiable in the state"),
    (InfiniteTransitionDensity, "model.transition_log_prob(s_next, s, a): expected finite or -inf (not NaN or +inf) "
                                "values, got 3 of 3"),
    (DistancePerCoordinate, "model.distance_to_goal(s): expected shape (3,) (one value per state: the states' leading "
                            "dimensions), got (3, 2)"),
    (FloatStateDim, "model.state_dim: expected an int attribute on FloatStateDim"),
    (NoActions, "model.n_actions: expected a positive int (the number of actions) on NoActions, got 0"),
    (NegativeActions, "model.n_actions: expected a positive int (the number of actions) on NegativeActions, got -3"),
    (BoolActions, "model.n_actions: expected a positive int (the number of actions) on BoolActions, got True"),
]


@pytest.mark.parametrize("cls, expected", PROBED, ids=[cls.__name__ for cls, _ in PROBED])
def test_a_target_that_breaks_the_protocol_is_refused_naming_the_method(cls, expected):
    message = one_line_error(lambda: built(f"env.model._target_={HERE}.{cls.__name__}"))
    assert message.startswith(f"env.model: {expected}"), message


# ---------------------------------------------------------------------------------------------
# escort_rl.train(..., model=obj)
# ---------------------------------------------------------------------------------------------

TINY = tiny_overrides("filter=sir", "trainer.iterations=1", "trainer.num_envs=2", "env.max_steps=4",
                      "num_particles=8", "actor.hidden=8")


class Unpicklable(Drift):
    def __init__(self) -> None:
        self.scale = lambda x: x


@pytest.mark.parametrize("overrides, model, expected", [
    (["+env.model.noise=1"], Drift(), "model: a model object is used as it is, so '+env.model.noise=1' would not "
                                      "reach it; drop it and set the value on the object itself"),
    ([f"env.model._target_={HERE}.Noisy"], Drift(), f"model: a model object is used as it is, so "
                                                    f"'env.model._target_={HERE}.Noisy' would not reach it"),
    ([], Unpicklable(), "model: Unpicklable cannot be pickled into the run directory (Can't pickle local object "),
    ([], f"{HERE}:Drift", "model.state_dim: expected an int attribute on str"),
    ([], NaNTransition(), "model.transition(s, a, generator): expected finite values"),
], ids=["a-model-key", "a-target", "unpicklable", "a-class-path-string", "fails-the-probe"])
def test_a_model_object_that_cannot_be_used_is_refused_before_anything_is_written(overrides, model, expected,
                                                                                  tmp_path):
    run = tmp_path / "run"
    message = one_line_error(lambda: escort_rl.train([*TINY, *overrides, f"output_dir={run}"], model=model,
                                                     progress=False))
    assert message.startswith(expected), message
    assert not run.exists()  # no model.pt, no config.yaml, no checkpoints

