"""Kickstarting (``trainer.kickstart_coef``): PPO's loss plus the cross-entropy to the scripted controller's
action on the same belief, with a weight that falls to 0 over ``trainer.kickstart_iterations``."""

import math

import pytest
import torch

from escort_rl.config import ConfigError, compose
from escort_rl.models import KidnappedRobot20D, LightDark10D, LightDark10DContinuous
from escort_rl.trainers.algorithm import trainer_params
from escort_rl.trainers.builders import make_env
from escort_rl.trainers.checkpointing import load_checkpoint
from escort_rl.trainers.params import PPOParams
from escort_rl.trainers.ppo import PPO, TEACHER_ACTION, kickstart_teacher
from escort_rl.trainers.training import train

TINY = ["trainer=ppo", "filter=sir", "trainer.warm_start_filter=null", "trainer.num_envs=4",
        "trainer.rollout_steps=12", "env.max_steps=12", "num_particles=8", "actor.hidden=16",
        "trainer.minibatches=2", "trainer.epochs=2", "trainer.critic_input=belief", "trainer.update_particles=null"]


def _ppo_and_batch(*overrides: str, model=None):
    """A tiny PPO with a kickstart teacher and one batch ``[E, T]`` its own policy collected, on ``model``
    (default: ``LightDark10D()``; the overrides pick its env group)."""
    torch.manual_seed(0)
    cfg = compose([*TINY, "trainer.teacher=scripted", *overrides])
    ppo = PPO(cfg, model if model is not None else LightDark10D())
    env = make_env(cfg, 4, seed=3)
    try:
        with torch.no_grad():
            batch = env.rollout(12, ppo.policy, break_when_any_done=False)
    finally:
        env.close()
    return ppo, batch


def _agreement(ppo, batch) -> float:
    """How often the policy's most probable action is the teacher's, over ``batch``'s frames."""
    with torch.no_grad():
        ppo.teacher(batch)
        greedy = ppo.policy.get_dist(batch).probs.argmax(-1)
    return float((greedy == batch[TEACHER_ACTION]).double().mean())


def test_the_teacher_term_is_the_weighted_cross_entropy_to_the_controllers_action():
    ppo, batch = _ppo_and_batch()
    try:
        ppo.kickstart = 0.25
        ppo.estimate_advantages(batch)
        ppo.teacher(batch)
        frames = batch.reshape(-1)
        out = ppo.loss_terms(frames)
        base = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
        cross_entropy = -ppo.policy.get_dist(frames).log_prob(frames[TEACHER_ACTION]).mean()
        total = ppo.total_loss(frames, out)
        assert float(total.detach()) == pytest.approx(float((base + 0.25 * cross_entropy).detach()), rel=1e-6)
        assert float(out["loss_kickstart"]) == pytest.approx(float(cross_entropy), rel=1e-6)
        ppo.kickstart = 0.0
        assert float(ppo.total_loss(frames, ppo.loss_terms(frames))) == pytest.approx(float(base), rel=1e-6)
    finally:
        ppo.close()


def test_kickstarted_updates_make_the_policy_act_as_the_teacher():
    """Updates with a large teacher weight take the greedy policy from chance agreement with the controller
    (about 1 in 10 actions) to most of its actions on the frames it trained on; the same updates without the
    teacher do not."""
    agreement = {}
    for weight in (0.0, 10.0):
        ppo, batch = _ppo_and_batch("trainer.entropy_coef=0", "trainer.lr=0.003")
        try:
            ppo.kickstart = weight
            for _ in range(60):
                ppo.update(batch.clone())
            agreement[weight] = _agreement(ppo, batch)
        finally:
            ppo.close()
    assert agreement[10.0] >= 0.8, agreement
    assert agreement[0.0] <= 0.6, agreement


def test_the_weight_falls_per_iteration_and_is_logged(tmp_path, capsys):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=3", "trainer.kickstart_coef=2.0", "trainer.kickstart_iterations=2",
                   "trainer.teacher=scripted",
                   f"output_dir={run}"]), progress=False)
    plan = "kickstarted by the scripted controller at gain 0.5, weight 2 falling to 0 by iteration 3"
    assert plan in capsys.readouterr().out
    history = load_checkpoint(run)["trainer_state"]["history"]
    assert [h["kickstart_weight"] for h in history] == [2.0, 1.0, 0.0]
    assert all(math.isfinite(h["loss_kickstart"]) for h in history[:2])
    assert "loss_kickstart" not in history[2]  # no teacher term once its weight is 0


@pytest.mark.parametrize("distribution", ["tanh_normal", "clipped_normal"])
def test_the_continuous_teacher_term_is_finite_at_the_edge_of_the_box(distribution):
    """The continuous controller's action is often clipped to the box's edge. A TanhNormal's density is 0 there,
    so the term reads it just inside; the clipped Gaussian (the default) puts mass on the edge, so the term is the
    cross-entropy to the action as it is. Either way the update stays finite."""
    ppo, batch = _ppo_and_batch("env=lightdark10d_continuous", f"actor.distribution={distribution}",
                                model=LightDark10DContinuous())
    try:
        ppo.kickstart = 1.0
        ppo.estimate_advantages(batch)
        ppo.teacher(batch)
        frames = batch.reshape(-1)
        assert bool((frames[TEACHER_ACTION].abs() >= ppo.model.action_high).any())  # some actions on the edge
        out = ppo.loss_terms(frames)
        assert math.isfinite(float(ppo.total_loss(frames, out).detach()))
        as_they_are = -ppo.policy.get_dist(frames).log_prob(frames[TEACHER_ACTION]).mean().detach()
        if distribution == "clipped_normal":
            assert float(out["loss_kickstart"]) == pytest.approx(float(as_they_are), rel=1e-6)
        else:
            assert float(out["loss_kickstart"]) != pytest.approx(float(as_they_are), rel=1e-3)
        metrics = ppo.update(batch)
        assert math.isfinite(metrics["kl_approx"]) and metrics["skipped_steps"] == 0
    finally:
        ppo.close()


def test_a_teacher_without_a_controller_is_refused():
    with pytest.raises(ConfigError, match="trainer.teacher: env 'kidnapped20d' has no scripted controller"):
        PPO(compose([*TINY, "env=kidnapped20d", "trainer.teacher=scripted"]), KidnappedRobot20D())


@pytest.mark.parametrize("overrides, teaches", [
    ([], True),  # Light-Dark's group marks its controller a teacher
    (["trainer.teacher=none"], False),
    (["trainer.kickstart_coef=0"], False),
    (["env.scripted_teacher=false"], False),
    (["env=kidnapped20d"], False),  # no controller, and its group marks none
])
def test_auto_kickstarts_where_the_env_group_marks_a_teacher(overrides, teaches):
    cfg = compose([*TINY, *overrides])
    model = KidnappedRobot20D() if "env=kidnapped20d" in overrides else LightDark10D()
    assert (kickstart_teacher(cfg, model, trainer_params(PPOParams, cfg.trainer)) is not None) is teaches


def test_recurrent_ppo_refuses_a_teacher():
    from escort_rl.trainers.recurrent_ppo import validate_recurrent_ppo_config

    cfg = compose(["trainer=recurrent_ppo", "trainer.teacher=scripted"])
    with pytest.raises(ConfigError, match="trainer.teacher: trainer=recurrent_ppo"):
        validate_recurrent_ppo_config(cfg)


@pytest.mark.parametrize("overrides, teacher, evaluation", [
    ([], 0.5, 0.125),  # Light-Dark's group: the teacher the default job learned from, the evaluation's best gain
    (["env.teacher_gain=null"], 0.125, 0.125),  # no teacher gain: the teacher is the evaluation's controller
    (["env.teacher_gain=2", "env.scripted_gain=1"], 2.0, 1.0),
])
def test_the_teacher_acts_at_its_own_gain_and_the_evaluation_at_the_best_one(overrides, teacher, evaluation):
    from escort_rl.trainers.builders import scripted_policy

    cfg = compose([*TINY, *overrides])
    model = LightDark10D()
    assert kickstart_teacher(cfg, model, trainer_params(PPOParams, cfg.trainer)).controller.gain_v == teacher
    assert scripted_policy(cfg, model).controller.gain_v == evaluation


def test_teacher_options_give_the_teacher_its_own_rule_and_leave_the_evaluation_alone():
    """``env.teacher_options``: the hidden goal's teacher looks at the beacon first ({confidence: 0.9}) while the
    evaluation's controller commits at once; on a belief split evenly over two modes the two act differently."""
    from escort_rl.models import HiddenGoal
    from escort_rl.trainers.builders import scripted_policy

    cfg = compose([*TINY, "env=hidden_goal", "env.model.dim=3", "env.model.modes=2", "trainer.teacher=scripted",
                   "env.teacher_options={confidence:0.9}"])
    model = HiddenGoal(dim=3, modes=2)
    teacher = kickstart_teacher(cfg, model, trainer_params(PPOParams, cfg.trainer))
    assert teacher.controller.confidence == 0.9 and scripted_policy(cfg, model).controller.confidence == 0.0
    goals = model.candidate_goals  # [2, 3]
    particles = torch.cat([torch.zeros(2, 3), goals], -1).unsqueeze(0)  # at the origin, one particle per mode
    look, commit = teacher.controller(particles, None), scripted_policy(cfg, model).controller(particles, None)
    beacon_push = scripted_policy(cfg, model).controller.model.beacon.abs().argmax()
    assert look.item() // 2 == beacon_push.item() and commit.item() != look.item()


@pytest.mark.parametrize("env, options, message", [
    ("env=hidden_goal", "{confidence:2}", "env.teacher_options: HeaviestModeController.confidence: must lie in"),
    ("env=hidden_goal", "{gain:1}", "env.teacher_options: .*takes the option 'confidence', not 'gain'"),
    ("env=lightdark10d", "{confidence:0.9}", "env.teacher_options: .*LightDark10D takes no options"),
])
def test_teacher_options_the_controller_does_not_take_name_the_key(env, options, message):
    from escort_rl.models import HiddenGoal

    # null first: the hidden goal's group sets its own options, and a mapping given on top merges into them
    cfg = compose([*TINY, env, "trainer.teacher=scripted", "env.teacher_options=null",
                   f"env.teacher_options={options}"])
    model = HiddenGoal() if env == "env=hidden_goal" else LightDark10D()
    with pytest.raises(ConfigError, match=message):
        kickstart_teacher(cfg, model, trainer_params(PPOParams, cfg.trainer))


def test_the_hidden_goal_teaches_with_its_look_first_rule_and_evaluates_the_committing_one():
    from escort_rl.models import HiddenGoal
    from escort_rl.trainers.builders import scripted_policy

    cfg = compose([*TINY, "env=hidden_goal"])  # teacher=auto: the group marks its rule a teacher
    model = HiddenGoal()
    assert kickstart_teacher(cfg, model, trainer_params(PPOParams, cfg.trainer)).controller.confidence == 0.999
    assert scripted_policy(cfg, model).controller.confidence == 0.0


def test_scripted_options_set_the_evaluation_s_controller_and_the_teacher_falls_back_to_them():
    from escort_rl.models import HiddenGoal
    from escort_rl.trainers.builders import scripted_policy

    model = HiddenGoal()
    cfg = compose([*TINY, "env=hidden_goal", "trainer.teacher=scripted", "env.scripted_options={confidence:0.5}",
                   "env.teacher_options=null"])  # the group's own teacher looks first at 0.999
    assert scripted_policy(cfg, model).controller.confidence == 0.5
    assert kickstart_teacher(cfg, model, trainer_params(PPOParams, cfg.trainer)).controller.confidence == 0.5
    cfg = compose([*TINY, "env=hidden_goal", "env.scripted_options={confidence:5}"])
    with pytest.raises(ConfigError, match="env.scripted_options: HeaviestModeController.confidence"):
        scripted_policy(cfg, model)


def test_teacher_options_must_be_a_mapping():
    with pytest.raises(ConfigError, match="env.teacher_options: expected a mapping of option names"):
        compose([*TINY, "env.teacher_options=3"])


def test_the_state_teacher_acts_on_the_true_state_of_each_training_frame():
    """``trainer.teacher=state``: the controller's action on each frame's ``true_state`` (a one-particle belief),
    whatever the particles say; the belief teacher's actions on the same frames differ where the belief is off."""
    from escort_rl.planners import TrueStateController

    ppo, batch = _ppo_and_batch("trainer.teacher=state")
    try:
        assert isinstance(ppo.teacher, TrueStateController)
        assert "on the true state" in ppo.plan_note()
        ppo.teacher(batch)
        expected = ppo.teacher.controller(batch["true_state"])
        assert torch.equal(batch[TEACHER_ACTION], expected)
        cfg = compose([*TINY, "trainer.teacher=scripted"])
        on_belief = kickstart_teacher(cfg, ppo.model, trainer_params(PPOParams, cfg.trainer))
        shuffled = batch.clone()
        shuffled["true_state"] = shuffled["true_state"].flip(0)  # another env's state, the same beliefs
        ppo.teacher(shuffled)
        assert not torch.equal(shuffled[TEACHER_ACTION], expected)
        on_belief(shuffled)
        assert torch.equal(shuffled[TEACHER_ACTION], on_belief(batch.clone())[TEACHER_ACTION])
    finally:
        ppo.close()
