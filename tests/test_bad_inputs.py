"""Bad inputs get one line naming the field, the argument or the model method, never a deep torch
error or a silently wrong result: belief shapes and dtypes, model outputs of the wrong shape or
dtype, filter and env constructor arguments of the wrong type, and the command line's output paths,
seeds and device."""

from __future__ import annotations

import pytest
import torch

from conftest import config_error
from escort_rl.belief import ESCORTFilter, ParticleBelief, SIRFilter, SVGDFilter
from escort_rl.envs import POMDPEnv
from escort_rl.models import LightDark10D, LinearGaussian

B, N, D = 2, 12, 3

FILTERS = {
    "sir": lambda: SIRFilter(),
    "svgd": lambda: SVGDFilter(num_steps=3),
    "escort": lambda: ESCORTFilter(num_steps=3),
}


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _inputs(filt, b: int = B, n: int = N):
    model = LinearGaussian(state_dim=D)
    belief = filt.init(model, (b,), n, gen(0))
    return model, belief, torch.zeros(b, dtype=torch.long), torch.full((b, D), 0.3)


def _one_line_error(fn) -> str:
    with pytest.raises(ValueError) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message, message
    return message


# ---------------------------------------------------------------------------------------------
# The input belief: shapes and dtypes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("shape", [(B, 1), (1, N), (B, N + 1)], ids=["one-column", "one-row", "one-too-many"])
def test_log_weights_of_another_shape_name_belief_log_weights(name, shape):
    """A [B, 1] or [1, N] log-weight tensor used to broadcast against the particles' [B, N] and give
    a belief without complaint."""
    filt = FILTERS[name]()
    model, belief, action, obs = _inputs(filt)
    bad = ParticleBelief(belief.particles, torch.zeros(shape))
    message = _one_line_error(lambda: filt.update(model, bad, action, obs, gen(1)))
    assert message.startswith(f"belief.log_weights: expected a floating-point tensor of shape {(B, N)}"), message
    assert f"got shape {shape}" in message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_integer_particles_name_belief_particles(name):
    filt = FILTERS[name]()
    model, belief, action, obs = _inputs(filt)
    bad = ParticleBelief(belief.particles.round().long(), belief.log_weights)
    message = _one_line_error(lambda: filt.update(model, bad, action, obs, gen(1)))
    assert message.startswith("belief.particles: expected a floating-point tensor"), message
    assert "torch.int64" in message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_a_float64_belief_of_a_float32_model_names_the_method_and_the_dtype(name):
    filt = FILTERS[name]()
    model, belief, action, obs = _inputs(filt)
    wide = ParticleBelief(belief.particles.double(), belief.log_weights.double())
    message = _one_line_error(lambda: filt.update(model, wide, action, obs, gen(1)))
    assert message.startswith("model.transition: fails on belief.particles of shape (2, 12, 3) and dtype "
                              "torch.float64"), message


# ---------------------------------------------------------------------------------------------
# Model methods that return the wrong shape or dtype
# ---------------------------------------------------------------------------------------------


class Misshapen(LinearGaussian):
    """A 3-D linear-Gaussian model whose ``transition`` or ``observation_log_prob`` returns the wrong
    shape or dtype (``kind``)."""

    def __init__(self, kind: str) -> None:
        super().__init__(state_dim=D)
        self.kind = kind
        self.observation_score = None  # the filters call observation_log_prob

    def transition(self, s, a, generator=None):
        out = super().transition(s, a, generator)
        if s.dim() == 3 and self.kind == "transition_drops_a_dimension":
            return out[..., :2]
        if s.dim() == 3 and self.kind == "transition_returns_ints":
            return out.round().long()
        return out

    def observation_log_prob(self, o, s_next, a):
        out = super().observation_log_prob(o, s_next, a)
        if self.kind == "log_prob_per_belief":
            return out[..., 0]
        if self.kind == "log_prob_with_a_trailing_axis":
            return out.unsqueeze(-1)
        return out


CULPRITS = {
    "transition_drops_a_dimension": "model.transition: returned shape (2, 12, 2)",
    "transition_returns_ints": "model.transition: returned shape (2, 12, 3), dtype torch.int64",
    "log_prob_per_belief": "model.observation_log_prob: returned shape (2,)",
    "log_prob_with_a_trailing_axis": "model.observation_log_prob: returned shape (2, 12, 1)",
}


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("kind", sorted(CULPRITS))
def test_a_model_output_of_the_wrong_shape_or_dtype_names_the_method(name, kind):
    filt = FILTERS[name]()
    _, belief, action, obs = _inputs(filt)
    message = _one_line_error(lambda: filt.update(Misshapen(kind), belief, action, obs, gen(1)))
    assert message.startswith(CULPRITS[kind]), message


def test_sir_refuses_a_log_likelihood_that_would_broadcast_silently():
    """With as many beliefs as particles, a [B, N, 1] log-likelihood broadcasts against the [B, N]
    log-weights without a torch error; SIR checks the shape itself."""
    filt = SIRFilter()
    _, belief, action, obs = _inputs(filt, b=4, n=4)
    message = _one_line_error(lambda: filt.update(Misshapen("log_prob_with_a_trailing_axis"), belief, action, obs))
    assert message.startswith("model.observation_log_prob: returned shape (4, 4, 1), dtype torch.float32, expected "
                              "a floating-point tensor of shape (4, 4)"), message


# ---------------------------------------------------------------------------------------------
# Constructor arguments of the wrong type
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch_shape", [(-1,), (2.5,), 2.5, (True,)], ids=["negative", "fraction", "float", "bool"])
def test_init_names_a_bad_batch_shape(batch_shape):
    message = _one_line_error(lambda: SIRFilter().init(LinearGaussian(state_dim=D), batch_shape, 8, gen(0)))
    assert message.startswith("batch_shape: expected a tuple of ints >= 0"), message


@pytest.mark.parametrize("kwargs, field", [(dict(resample_threshold="0.5"), "resample_threshold"),
                                           (dict(roughening=None), "roughening"),
                                           (dict(roughening="0.1"), "roughening")],
                         ids=["threshold-str", "roughening-none", "roughening-str"])
def test_sir_arguments_that_are_not_numbers_are_named(kwargs, field):
    message = _one_line_error(lambda: SIRFilter(**kwargs))
    assert message == f"SIRFilter.{field}: expected a number, got {kwargs[field]!r}"


@pytest.mark.parametrize("kwargs, expected", [
    (dict(batch_size=2.5), "POMDPEnv.batch_size: every size must be a positive int, got 2.5"),
    (dict(batch_size=(True,)), "POMDPEnv.batch_size: every size must be a positive int, got (True,)"),
    (dict(max_steps=2.5), "POMDPEnv.max_steps: must be a positive int or None, got 2.5"),
    (dict(max_steps=0), "POMDPEnv.max_steps: must be a positive int or None, got 0"),
    (dict(seed=2.5), "POMDPEnv.seed: must be an int or None, got 2.5"),
    (dict(device="tpu"), "POMDPEnv.device: not a device: 'tpu'; use 'cpu', 'cuda' or 'cuda:N'"),
], ids=["batch-float", "batch-bool", "max-steps-fraction", "max-steps-zero", "seed-fraction", "device-unknown"])
def test_pomdp_env_names_a_bad_argument(kwargs, expected):
    assert _one_line_error(lambda: POMDPEnv(LightDark10D(), **kwargs)) == expected


def test_pomdp_env_names_a_cuda_device_this_machine_lacks():
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    message = _one_line_error(lambda: POMDPEnv(LightDark10D(), device="cuda:99"))
    assert message == (f"POMDPEnv.device: 'cuda:99' but this machine has {count} CUDA device(s); "
                       "use device='cpu'")


# ---------------------------------------------------------------------------------------------
# The config: output_dir, seeds, rates, interpolations, exploring starts, the logger
# ---------------------------------------------------------------------------------------------




def test_an_empty_output_dir_is_refused_instead_of_writing_into_the_working_directory():
    assert config_error(["output_dir=''"]).startswith("config: output_dir: empty; pass a folder")


def test_an_output_dir_inside_a_folder_that_cannot_be_written_is_named(tmp_path, monkeypatch):
    from escort_rl.config import schema

    monkeypatch.setattr(schema.os, "access", lambda path, mode: False)
    message = config_error([f"output_dir={tmp_path / 'run'}"])
    assert message == (f"config: output_dir: '{tmp_path / 'run'}' cannot be written: '{tmp_path}' is not writable; "
                       "pass a folder you can write to")


def test_a_seed_torch_cannot_take_is_named():
    message = config_error(["seed=99999999999999999999999"])
    assert message == "config: seed: must be < 9223372036854775808, got 99999999999999999999999"


def test_a_learning_rate_that_overflows_adams_first_step_is_named():
    assert config_error(["trainer.lr=1e38"]) == "config: trainer.lr: must be < 1e+37, got 1e+38"


def test_an_interpolation_that_does_not_resolve_names_its_key(monkeypatch):
    monkeypatch.delenv("ESCORT_RL_TEST_UNSET", raising=False)
    message = config_error(["output_dir=${oc.env:ESCORT_RL_TEST_UNSET}"])
    assert message.startswith("config: output_dir: KeyError raised while resolving interpolation"), message
    assert "ESCORT_RL_TEST_UNSET" in message


@pytest.mark.parametrize("overrides, expected", [
    (["env.exploring_starts.start_high=abc"], "env.exploring_starts.start_high: expected a number, got 'abc'"),
    (["+env.exploring_starts.nokey=1"], "env.exploring_starts.nokey: not a key of env.model"),
    (["env=mtt20d", "env.exploring_starts.agent_start_halfwidth=-1"],
     "env.exploring_starts.agent_start_halfwidth: must be >= 0, got -1.0"),
], ids=["wrong-type", "unknown-key", "out-of-range"])
def test_exploring_starts_are_checked_against_the_model_schema(overrides, expected):
    """A bad exploring-start value used to reach the model's constructor (a TypeError traceback)."""
    from escort_rl.config import ConfigError, compose
    from escort_rl.trainers.validation import validate_train_config

    with pytest.raises(ConfigError) as info:
        validate_train_config(compose(overrides))
    assert str(info.value).startswith(expected), str(info.value)


def test_the_tensorboard_logger_without_tensorboard_is_named(monkeypatch):
    import escort_rl.trainers.validation as validation
    from escort_rl.config import ConfigError, compose

    real = validation.importlib.util.find_spec
    monkeypatch.setattr(validation.importlib.util, "find_spec",
                        lambda name, *a: None if name == "tensorboard" else real(name, *a))
    with pytest.raises(ConfigError, match=r"^logger.backend: 'tensorboard' needs the tensorboard package"):
        validation.validate_train_config(compose(["logger.backend=tensorboard"]))


# ---------------------------------------------------------------------------------------------
# The run directory
# ---------------------------------------------------------------------------------------------


def test_a_run_directory_that_cannot_be_created_names_output_dir(tmp_path, monkeypatch):
    from pathlib import Path

    from escort_rl.config import ConfigError
    from escort_rl.trainers.scaffold import make_run_dir

    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", refuse)
    with pytest.raises(ConfigError) as info:
        make_run_dir(tmp_path / "run")
    assert str(info.value) == (f"output_dir: cannot create '{tmp_path / 'run'}' (Permission denied); pass a folder "
                               "you can write to")


def test_output_dir_with_a_tilde_puts_the_whole_run_in_the_home_folder(tmp_path, monkeypatch):
    """``output_dir='~/run'`` used to put the checkpoints in $HOME/run but config.yaml, the logs and
    history.json in a folder literally named '~' under the working directory."""
    from escort_rl.config import compose
    from escort_rl.trainers.training import train

    home, cwd = tmp_path / "home", tmp_path / "cwd"
    home.mkdir()
    cwd.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(cwd)
    cfg = compose(["trainer.iterations=1", "trainer.warm_start_filter=null", "trainer.num_envs=2", "env.max_steps=3",
                   "num_particles=8", "actor.hidden=8", "filter.compile=false", "output_dir='~/run'"])
    run_dir = train(cfg, progress=False)
    assert run_dir == home / "run"
    for name in ("config.yaml", "history.json", "checkpoints", "logs"):
        assert (home / "run" / name).exists(), name
    assert list(cwd.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# Command-line arguments
# ---------------------------------------------------------------------------------------------


def _cli_error(argv, capsys) -> str:
    from escort_rl.cli import main

    assert main(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.mark.parametrize("argv, expected", [
    (["bench", "cost", "--device", "cuda:99"], "error: --device: 'cuda:99' but this machine has"),
    (["bench", "cost", "--max-pairs", "nan"], "error: --max-pairs: must be a finite number > 0, got nan"),
    (["bench", "throughput", "--collector-workers", "3", "--num-envs", "2"],
     "error: --collector-workers: 3 does not divide --num-envs 2"),
    (["bench", "synthetic", "--methods", "nope"], "error: --methods: unknown name 'nope'; choose from escort"),
    (["bench", "synthetic", "--targets", "nope"], "error: --targets: unknown name 'nope'; choose from gmm1d"),
    (["bench", "scaling", "--structures", "nope"], "error: --structures: unknown structure 'nope'; choose from block"),
], ids=["device", "max-pairs", "workers", "methods", "targets", "structures"])
def test_bench_arguments_are_named_before_any_work(argv, expected, capsys):
    assert _cli_error(argv, capsys).startswith(expected)


def test_output_arguments_that_cannot_hold_results_are_named(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert _cli_error(["bench", "cost", "--output", str(a_file)], capsys) == (
        f"error: --output: '{a_file}' is an existing file; pass a folder")
    assert _cli_error(["bench", "cost", "--output", str(a_file / "sub")], capsys) == (
        f"error: --output: '{a_file / 'sub'}' is under the file '{a_file}'; pass a folder")
    assert _cli_error(["evaluate", "--checkpoint", str(tmp_path), "--output", str(a_file)], capsys) == (
        f"error: --output: '{a_file}' is an existing file; pass a folder")
    assert _cli_error(["bench", "throughput", "--output", str(a_file)], capsys) == (
        f"error: --output: '{a_file}' is an existing file; pass a folder")


def test_an_output_folder_that_cannot_be_created_is_named(tmp_path, monkeypatch, capsys):
    from pathlib import Path

    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", refuse)
    assert _cli_error(["bench", "cost", "--output", str(tmp_path / "out")], capsys) == (
        f"error: --output: cannot create '{tmp_path / 'out'}' (Permission denied); pass a folder you can write to")


def test_a_non_finite_training_loss_ends_the_command_with_its_line(monkeypatch, capsys):
    import escort_rl.cli as cli

    def diverge(overrides, quiet=False):
        raise FloatingPointError("training: non-finite loss_critic at iteration 3; lower trainer.lr or check the "
                                 "model's rewards (last checkpoint kept)")

    monkeypatch.setattr(cli, "_train", diverge)
    assert _cli_error(["train", "--quiet"], capsys) == (
        "error: training: non-finite loss_critic at iteration 3; lower trainer.lr or check the model's rewards "
        "(last checkpoint kept)")


def test_a_worker_whose_exit_status_is_read_late_still_ends_the_run_with_its_line(tmp_path):
    """A killed worker's pipe closes a moment before its exit status can be read: the iteration fails
    with an EOFError while the worker still looks alive. The run must still end with the one line
    naming the worker, not the EOFError's traceback."""
    from types import SimpleNamespace

    from escort_rl.trainers.scaffold import CollectorWorkerDied, raise_if_worker_died

    class LateProc:
        pid = 4242

        def __init__(self):
            self.reads = 0

        @property
        def exitcode(self):
            self.reads += 1
            return None if self.reads < 4 else -9

    class AliveProc:
        pid, exitcode = 4343, None

    collector = SimpleNamespace(procs=[LateProc(), AliveProc()])
    algorithm = SimpleNamespace(collectors=SimpleNamespace(collector=collector))
    with pytest.raises(CollectorWorkerDied) as info:
        raise_if_worker_died(algorithm, 2, tmp_path / "checkpoints" / "checkpoint-1", tmp_path)
    assert str(info.value).startswith("collector: worker 0 (pid 4242) killed by SIGKILL during iteration 2;")


def test_no_dead_worker_lets_the_iteration_error_through(tmp_path):
    from types import SimpleNamespace

    from escort_rl.trainers.scaffold import raise_if_worker_died

    alive = SimpleNamespace(pid=1, exitcode=None)
    algorithm = SimpleNamespace(collectors=SimpleNamespace(collector=SimpleNamespace(procs=[alive])))
    assert raise_if_worker_died(algorithm, 2, None, tmp_path, wait_s=0.05) is None
    single = SimpleNamespace(collectors=SimpleNamespace(collector=SimpleNamespace()))  # no worker processes
    assert raise_if_worker_died(single, 2, None, tmp_path) is None


def test_weights_are_not_sent_to_a_collector_with_a_dead_worker():
    """TorchRL waits for every worker's acknowledgement of new weights without a timeout: sending them
    to a collector whose worker died hung the run instead of ending it with the worker's line."""
    from types import SimpleNamespace

    from escort_rl.trainers.scaffold import StagedCollector

    sent = []
    workers = [SimpleNamespace(pid=1, exitcode=None), SimpleNamespace(pid=2, exitcode=None)]
    collector = SimpleNamespace(procs=workers, update_policy_weights_=lambda: sent.append(True))
    staged = StagedCollector(cfg=None, build=None, filter_at=None)
    staged.collector = collector
    staged.update_policy_weights()
    assert sent == [True]
    workers[1].exitcode = -9
    with pytest.raises(RuntimeError, match="^collector: a worker process has ended$"):
        staged.update_policy_weights()
    assert sent == [True]


def test_a_worker_that_dies_while_weights_are_sent_ends_the_wait():
    """TorchRL's weight send waits for each worker's acknowledgement forever; a worker that dies
    during the send must end the wait with the error the scaffold names, not hang the run."""
    import threading
    from types import SimpleNamespace

    from escort_rl.trainers.scaffold import StagedCollector

    release = threading.Event()

    class DiesDuringSend:
        pid = 7

        def __init__(self):
            self.sending, self.reads = False, 0

        @property
        def exitcode(self):
            if not self.sending:
                return None
            self.reads += 1
            return None if self.reads < 3 else -9

    worker = DiesDuringSend()

    def send_and_wait_for_acks():
        worker.sending = True
        release.wait()  # the dead worker's acknowledgement never comes

    staged = StagedCollector(cfg=None, build=None, filter_at=None)
    staged.collector = SimpleNamespace(procs=[worker], update_policy_weights_=send_and_wait_for_acks)
    try:
        with pytest.raises(RuntimeError, match="^collector: a worker process has ended$"):
            staged.update_policy_weights(poll_s=0.01)
    finally:
        release.set()
