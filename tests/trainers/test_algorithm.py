"""The trainers' base classes (escort_rl.trainers.algorithm, PPOBase) and the resume decisions
(escort_rl.trainers.resume): the hooks a subclass must give, the update PPO and recurrent PPO share,
the attributes every method reads, and a resume's output_dir."""

import ast
import inspect
import textwrap
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import escort_rl
from escort_rl.config import ConfigError, compose
from escort_rl.models import LightDark10D
from escort_rl.trainers import resume
from escort_rl.trainers.algorithm import Algorithm
from escort_rl.trainers.ppo import PPO, PPOBase
from escort_rl.trainers.recurrent_ppo import RecurrentPPO
from escort_rl.trainers.reinforce import Reinforce
from escort_rl.trainers.scaffold import CollectorAlgorithm, StagedCollector, run_training
from escort_rl.trainers.training import train

TINY_PPO = ["trainer=ppo", "filter=sir", "trainer.warm_start_filter=null", "trainer.num_envs=4",
            "trainer.rollout_steps=6", "env.max_steps=12",
            "num_particles=8", "actor.hidden=8", "trainer.minibatches=2", "trainer.epochs=2"]
TINY_REINFORCE = ["trainer=reinforce", "trainer.num_envs=4", "env.max_steps=12", "num_particles=16",
                  "actor.hidden=16", "trainer.minibatch_size=64", "trainer.checkpoint_every=1", "filter.compile=false"]


def _recurrent_cfg():
    try:
        cfg = compose(["trainer=recurrent_ppo", *TINY_PPO[1:]])
    except ConfigError:  # a schema without the recurrent trainer: the PPO config with its keys
        cfg = compose(TINY_PPO)
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    cfg.trainer.algorithm, cfg.trainer.hidden = "recurrent_ppo", 8
    return cfg


# ------------------------------------------------------------------------------------ the hooks
def test_an_algorithm_without_a_hook_cannot_be_built():
    class NoIteration(Algorithm):
        @property
        def components(self):
            return {}

        def close(self):
            pass

    with pytest.raises(TypeError, match="iteration"):
        NoIteration(None)

    class NoComponents(CollectorAlgorithm):
        def iteration(self, index, seed):
            return {"frames": 0}

    with pytest.raises(TypeError, match="components"):
        NoComponents(None, None, build_collector=None)


def test_a_ppo_variant_without_its_hooks_cannot_be_built():
    class NoMinibatches(PPOBase):
        @property
        def components(self):
            return {}

        def make_env_factory(self, cfg, num_envs, seed):
            return None

        def fill(self, batch):
            return batch

    with pytest.raises(TypeError, match="minibatches"):
        NoMinibatches(compose(TINY_PPO), LightDark10D(), policy=None, loss=None)


def test_run_training_refuses_an_object_that_is_not_an_algorithm(tmp_path):
    class Duck:
        components = {}

        def iteration(self, index, seed):
            return {"frames": 0}

        def close(self):
            pass

    cfg = compose([*TINY_REINFORCE, "trainer.iterations=1", f"output_dir={tmp_path}"])
    with pytest.raises(TypeError, match="^run_training: Duck is not an escort_rl.trainers.algorithm.Algorithm; "):
        run_training(cfg, Duck(), progress=False)
    assert not (tmp_path / "config.yaml").exists()  # refused before anything was written


def test_ppo_and_recurrent_ppo_share_the_update_and_the_iteration():
    for name in ("update", "iteration", "epochs_for", "total_loss"):
        assert getattr(PPO, name) is getattr(PPOBase, name), name
        assert getattr(RecurrentPPO, name) is getattr(PPOBase, name), name
    # where they differ: the hooks
    for name in ("fill", "minibatches", "make_env_factory"):
        assert getattr(PPO, name) is not getattr(RecurrentPPO, name), name
    assert RecurrentPPO.prepare is not PPOBase.prepare and PPO.prepare is PPOBase.prepare


def _self_reads(cls) -> set[str]:
    """The attributes ``self.X`` that the methods of ``cls`` (its own body) read."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    return {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name) and node.value.id == "self" and isinstance(node.ctx, ast.Load)}


@pytest.mark.parametrize("build", [
    lambda: PPO(compose(TINY_PPO), LightDark10D()),
    lambda: PPO(compose([*TINY_PPO, "trainer.action_repeat=3"]), LightDark10D()),
    lambda: RecurrentPPO(_recurrent_cfg(), LightDark10D()),
    lambda: Reinforce(compose(TINY_REINFORCE), LightDark10D()),
], ids=["ppo", "ppo-repeat", "recurrent_ppo", "reinforce"])
def test_every_attribute_a_method_reads_is_set_by_the_constructors(build):
    algorithm = build()
    try:
        assert isinstance(algorithm.collectors, StagedCollector)
        for cls in type(algorithm).__mro__:
            if cls.__module__.startswith("escort_rl."):
                missing = sorted(a for a in _self_reads(cls) if not hasattr(algorithm, a))
                assert not missing, f"{cls.__name__} reads {missing}, which no constructor set"
        assert sorted(algorithm.components) == ["actor", "critic", "optimizer"]  # the checkpoint's keys
    finally:
        algorithm.close()


def test_ppo_batch_sizes_come_from_the_base():
    algorithm = PPO(compose([*TINY_PPO, "trainer.action_repeat=5"]), LightDark10D())
    recurrent = RecurrentPPO(_recurrent_cfg(), LightDark10D())
    # 12 steps / 5 per decision = 3 decisions per episode: one batch of 3 decisions per env
    assert (algorithm.repeat, algorithm.rollout_steps, algorithm.batches, algorithm.frames_per_batch) == (5, 3, 1, 12)
    assert (recurrent.repeat, recurrent.rollout_steps, recurrent.batches, recurrent.frames_per_batch) == (1, 6, 2, 24)
    assert algorithm.minibatch == 6 and recurrent.optimizer.param_groups[0]["params"]


# ------------------------------------------------------------------------------------ resume
def test_output_dir_agreement_is_checked_in_one_place():
    message = "is not the run directory being resumed"
    hits = [p for p in Path(escort_rl.__file__).parent.rglob("*.py") if message in p.read_text()]
    assert [p.name for p in hits] == ["resume.py"]
    with pytest.raises(ConfigError, match=r"^output_dir: 'elsewhere' is not the run directory being resumed "
                                          r"\('runs/a'\); .*drop output_dir=, or copy the run directory"):
        resume.check_output_dir("elsewhere", Path("runs/a"))
    resume.check_output_dir("runs/a/", Path("runs/a"))  # the same directory, written differently


def test_a_new_run_records_its_overrides():
    for overrides in (["trainer.iterations=3"], ["resume=null", "trainer.iterations=3"]):
        cfg, saved = resume.train_config(overrides)
        assert saved is None and list(cfg.overrides) == ["trainer.iterations=3"] and cfg.trainer.iterations == 3


def test_resume_writes_into_the_run_it_continues(tmp_path):
    run, other = tmp_path / "run", tmp_path / "other"
    cfg, _ = resume.train_config([*TINY_REINFORCE, "trainer.iterations=1", f"output_dir={run}"])
    train(cfg, progress=False)

    with pytest.raises(ConfigError, match=r"^output_dir: .* drop output_dir=, or copy the run directory"):
        resume.train_config([f"resume={run}", f"output_dir={other}"])
    cfg, saved = resume.train_config([f"resume={run}", "trainer.iterations=2"])
    assert cfg.output_dir == str(run) and cfg.resume == saved["path"] and saved["trainer_state"]["iteration"] == 1

    moved = tmp_path / "moved"
    run.rename(moved)  # a moved run writes into where it is now
    cfg, saved = resume.train_config([f"resume={moved}"])
    assert cfg.output_dir == str(moved) and cfg.overrides[-1] == f"output_dir='{moved}'"
    assert f"output_dir={run}" not in cfg.overrides
    cfg.output_dir = str(other)
    with pytest.raises(ConfigError, match="^output_dir: "):
        resume.restore(cfg, {}, saved)
    assert not other.exists()
