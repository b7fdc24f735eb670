"""``escort-rl bench frontier --model pkg.module:Class --model-arg KEY=VALUE`` refuses a mistake with one
line naming ``--model``, ``--model-arg`` or the model method, before any cell runs: a class path that is
not ``pkg.module:Class``, a module that fails to import, an attribute that is not a class, keyword
arguments that are malformed, repeated, unknown or out of range, values that do not parse, and a model
that fails the model protocol's probe (a frontier on a detached likelihood used to run and rank filters
that ignored the observations)."""

from __future__ import annotations

import textwrap

import pytest

from conftest import DRIFT_MODEL_SOURCE
from escort_rl.cli import main

USER_MODELS = DRIFT_MODEL_SOURCE + textwrap.dedent('''
    class Detached(Drift):
        def observation_log_prob(self, o, s_next, a):
            return super().observation_log_prob(o, s_next.detach(), a)

    class FloatTerminal(Drift):
        def is_terminal(self, s):
            return torch.zeros(s.shape[:-1])

    def not_a_model():
        return 42

    scale = 3.0
''')

MODULES = {
    "frontier_user_models": USER_MODELS,
    "frontier_body_fails": "raise RuntimeError('weights file missing')\n",
    "frontier_syntax_error": "class Model(:\n    pass\n",
}


@pytest.fixture
def user_models(tmp_path, monkeypatch):
    for name, source in MODULES.items():
        (tmp_path / f"{name}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def frontier_error(argv: list[str], out, capsys) -> str:
    """The one line ``bench frontier`` prints for ``argv`` (exit status 2), with nothing measured."""
    capsys.readouterr()
    status = main(["bench", "frontier", *argv, "--quick", "--methods", "sir", "--sir-particles", "10",
                   "--reference-particles", "50", "--steps", "2", "--output", str(out)])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert status == 2 and len(lines) == 1, (status, lines)
    assert not (out / "cells").exists() and not (out / "frontier.json").exists()
    return lines[0]


M = "frontier_user_models"


@pytest.mark.parametrize("argv, expected", [
    (["--model", f"{M}.Drift"], f"error: --model: expected pkg.module:Class (or env=NAME), got '{M}.Drift'"),
    (["--model", f"{M}:"], f"error: --model: expected pkg.module:Class (or env=NAME), got '{M}:'"),
    (["--model", ":Drift"], "error: --model: expected pkg.module:Class (or env=NAME), got ':Drift'"),
    (["--model", "frontier_body_fails:Model"],
     "error: --model: cannot import frontier_body_fails:Model (RuntimeError: weights file missing)"),
    (["--model", "frontier_syntax_error:Model"],
     "error: --model: cannot import frontier_syntax_error:Model (SyntaxError: "),
    (["--model", f"{M}:scale"], f"error: --model: {M}:scale is a float, not a class; name the model's class"),
    (["--model", f"{M}:torch"], f"error: --model: {M}:torch is a module, not a class; name the model's class"),
], ids=["dots-for-the-colon", "no-class", "no-module", "module-body-fails", "syntax-error", "a-number", "a-module"])
def test_a_class_path_that_does_not_name_a_class_is_refused(argv, expected, user_models, tmp_path, capsys):
    assert frontier_error(argv, tmp_path / "out", capsys).startswith(expected)


@pytest.mark.parametrize("args, expected", [
    (["obs_std"], "error: --model-arg: 'obs_std' is not of the form KEY=VALUE"),
    (["=0.3"], "error: --model-arg: '=0.3' is not of the form KEY=VALUE"),
    (["obs_std=0.1", "obs_std=0.2"], "error: --model-arg: obs_std is given twice; give each keyword once"),
    (["sigma=0.3"], "error: --model-arg: Drift(sigma) failed: Drift.__init__() got an unexpected keyword argument "
                    "'sigma'; check the keywords and values against the class"),
    (["obs_std=abc"], "error: --model-arg: Drift(obs_std) failed: could not convert string to float: 'abc'"),
    (["obs_std=-1"], "error: --model-arg: Drift(obs_std) failed: obs_std must be > 0, got -1"),
    (["obs_std=[1,"], "error: --model-arg: cannot read the value '[1,' ("),
], ids=["no-equals", "no-key", "repeated", "unknown-keyword", "not-a-number", "out-of-range", "does-not-parse"])
def test_a_model_argument_that_does_not_fit_is_refused(args, expected, user_models, tmp_path, capsys):
    argv = ["--model", f"{M}:Drift", "--model-arg", *args]
    assert frontier_error(argv, tmp_path / "out", capsys).startswith(expected)


@pytest.mark.parametrize("cls, expected", [
    ("Detached", "error: model.observation_log_prob(o [B, 1, obs_dim], particles [B, N, d], a [B, N]): not "
                 "differentiable in the state"),
    ("FloatTerminal", "error: model.is_terminal(s): expected dtype torch.bool, got torch.float32"),
    ("not_a_model", "error: model.state_dim: expected an int attribute on int; a model must follow "
                    "escort_rl.models.POMDPModel"),
], ids=["detached-likelihood", "float-terminal", "a-function-returning-a-number"])
def test_a_model_that_fails_the_probe_is_refused_before_any_cell(cls, expected, user_models, tmp_path, capsys):
    assert frontier_error(["--model", f"{M}:{cls}"], tmp_path / "out", capsys).startswith(expected)
