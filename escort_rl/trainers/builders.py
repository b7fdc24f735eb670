"""Build models, filters, environments and policies from a config; the names a config uses map to
classes in :mod:`escort_rl.config.registry`."""

from __future__ import annotations

from functools import partial

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import ProbabilisticActor

from escort_rl.config import ConfigError, registry
from escort_rl.config.errors import first_line
from escort_rl.envs import POMDPEnv
from escort_rl.models.protocol import is_continuous
from escort_rl.modules import DeepSetsActor, DeepSetsCritic, make_deepsets_policy, policy_outputs
from escort_rl.modules.action_heads import DEFAULT_MIN_SCALE, SAVED_RUN_DISTRIBUTION
from escort_rl.planners import ScriptedBeliefController, TrueStateController
from escort_rl.planners.scripted import DEFAULT_GAIN_V, scripted_controller_for
from escort_rl.transforms import ActionRepeat, BeliefTransform


def _kwargs(node, exclude: tuple[str, ...] = ("name",)) -> dict:
    data = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node)
    return {k: v for k, v in data.items() if k not in exclude}


def _instantiate(target: str, kwargs: dict, where: str, **extra):
    """``hydra.utils.instantiate({"_target_": target, **kwargs}, **extra)``; returns the object, or
    raises the constructor's own exception (``TypeError``, ``ValueError``), or :class:`ConfigError`
    naming ``where._target_`` when the target cannot be imported."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate({"_target_": target, **kwargs}, **extra, _convert_="all")
    except InstantiationException as err:
        cause = err.__cause__
        if cause is None:  # located, but hydra cannot call it
            raise ConfigError(f"{where}._target_: '{target}' is not a class or a function "
                              f"({first_line(err)}); name a class, e.g. my_pkg.models.MyModel") from None
        if isinstance(cause, ImportError):
            raise ConfigError(f"{where}._target_: cannot import '{target}'{_import_reason(target, cause)}") from None
        raise cause from None


def _import_reason(target: str, err: ImportError) -> str:
    """Why ``target`` does not import, when that is not simply that it is not there: its module fails
    (an error in its body, a dependency it imports is missing), as `` (Type: first line)``."""
    origin = err.__cause__ or err
    if isinstance(origin, ModuleNotFoundError) and origin.name and target.startswith(origin.name):
        return ""  # the module or class itself is not there
    if isinstance(origin, (ImportError, AttributeError)) and origin is err:
        return ""
    return f" ({type(origin).__name__}: {first_line(origin)})"


def _prefixed(where: str, err: Exception) -> str:
    """The first line of ``err``, led by ``where`` unless it already names it."""
    line = str(err).splitlines()[0]
    return line if line.startswith(where) else f"{where}: {line}"


def build_model(env_cfg: DictConfig, device: str | torch.device = "cpu", densities: bool = True):
    """The POMDP model of ``env.model._target_`` (configs saved without one: the model named by
    ``env.name``) with the other keys of ``env.model`` as keyword arguments, and ``device`` when
    the target takes it. The result is checked against the model protocol
    (:func:`escort_rl.models.check_model`; ``densities=False``: as a simulator, for the envs' own model
    where it differs from the filter's). ``env=popgym`` has no model: its task's spaces
    (:class:`~escort_rl.models.TaskSpaces`), all a model-free trainer reads."""
    from escort_rl.models import check_model

    if registry.is_task_only(env_cfg.get("name")):
        return build_task_spaces(env_cfg, device)

    model_cfg = env_cfg.get("model") or {}
    if OmegaConf.is_config(model_cfg) and OmegaConf.is_missing(model_cfg, "_target_"):
        raise ConfigError("env.model._target_: missing (???); name your model's class, e.g. env=custom "
                          "env.model._target_=my_pkg.models.MyModel +env.model.KEY=VALUE")
    target = model_cfg.get("_target_")
    if target is None:
        target = registry.target("model", env_cfg.name)
    extra = {"device": device} if _takes(target, "device") else {}
    try:
        model = _instantiate(target, _kwargs(model_cfg, exclude=("_target_",)), "env.model", **extra)
        check_model(model, densities=densities)
    except (TypeError, ValueError) as err:
        raise ConfigError(_prefixed("env.model", err)) from None
    except RuntimeError as err:  # e.g. a torch error in the model's constructor
        raise ConfigError(f"env.model: building '{target}' raised {type(err).__name__}: {first_line(err)}") from None
    return model


def build_task_spaces(env_cfg: DictConfig, device: str | torch.device = "cpu"):
    """The :class:`~escort_rl.models.TaskSpaces` of ``env=popgym``'s ``env.popgym_task``."""
    from escort_rl.envs.popgym import popgym_task_spaces

    task = env_cfg.get("popgym_task", None)
    if not task:
        raise ConfigError("env.popgym_task: env=popgym trains in one of POPGym's tasks; name it, e.g. "
                          "env.popgym_task=RepeatPreviousEasy")
    try:
        return popgym_task_spaces(str(task), str(device))
    except (ImportError, ValueError) as err:
        raise ConfigError(f"env.popgym_task: {str(err).splitlines()[0].removeprefix('name: ')}") from None


def _takes(target: str, name: str) -> bool:
    """Whether the callable at dotted path ``target`` takes a keyword ``name`` (or ``**kwargs``);
    ``True`` when it cannot be imported here (instantiating then names the failure)."""
    import importlib
    import inspect

    parts = str(target).split(".")
    obj = None
    for i in range(len(parts) - 1, 0, -1):  # the longest importable module prefix, then attributes
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        except Exception:  # noqa: BLE001 - the module's body fails: instantiate names it
            return True
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return True
        break
    try:
        params = inspect.signature(obj).parameters.values()
    except (TypeError, ValueError):  # not found, or no signature: instantiate reports it
        return True
    return any(p.name == name or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def build_filter(filter_cfg: DictConfig):
    """The belief filter of class ``filter._target_`` (configs saved without one: the class of
    ``filter.kind``) with the keys other than ``_target_``, ``name`` and ``kind`` as keyword arguments
    (``name`` labels a configuration, e.g. ``escort_nocorr``)."""
    target = filter_cfg.get("_target_")
    if target is None:
        target = registry.target("filter", filter_cfg.get("kind", filter_cfg.name))
    try:
        return _instantiate(target, _kwargs(filter_cfg, exclude=("_target_", "name", "kind")), "filter")
    except (TypeError, ValueError) as err:
        raise ConfigError(_prefixed("filter", err)) from None


def make_filter(name: str, **overrides):
    """The belief filter of the config option ``name`` (``configs/filter/<name>.yaml``: ``"sir"``,
    ``"escort_train"``, ...), built as a run with ``filter=<name>`` builds it, with ``overrides`` (the
    option's keys, e.g. ``num_steps=10``) on top. ``ConfigError`` names an unknown option or key.

    Example:
        >>> import escort_rl
        >>> f = escort_rl.make_filter("escort_train", compile=False)
        >>> type(f).__name__, f.num_steps
        ('ESCORTFilter', 15)
    """
    from omegaconf.errors import OmegaConfBaseException

    from escort_rl.config import compose
    from escort_rl.config.checking import check_config, describe_error

    node = compose([f"filter={name}"]).filter
    try:
        node = OmegaConf.merge(node, overrides)
        check_config(node)
    except OmegaConfBaseException as err:
        raise ConfigError(_prefixed("filter", ValueError(describe_error(err)))) from None
    except ConfigError as err:
        raise ConfigError(_prefixed("filter", err)) from None
    return build_filter(node)


def make_env(cfg: DictConfig, num_envs: int, seed: int | None = None, action_repeat: int = 1) -> TransformedEnv:
    """``TransformedEnv(POMDPEnv(model, (num_envs,)), BeliefTransform(model, filter, N))``, followed
    by :class:`~escort_rl.transforms.ActionRepeat` when ``action_repeat > 1`` (a policy's decision
    then holds for that many env steps, each with its belief update).

    Module-level (and picklable through ``functools.partial``) so that spawned collector workers
    can build it. The belief transform shares the env's generator, so ``env.set_seed`` seeds both.
    """
    model = build_model(cfg.env, cfg.device)
    base = build_pomdp_env(cfg, num_envs, seed, model)
    particles_key, log_weights_key = belief_keys(cfg)
    belief = BeliefTransform(model, build_filter(cfg.filter), int(cfg.num_particles),
                             particles_key=particles_key, log_weights_key=log_weights_key)
    return TransformedEnv(base, Compose(belief, ActionRepeat(action_repeat)) if action_repeat > 1 else belief)


def build_pomdp_env(cfg: DictConfig, num_envs: int, seed: int | None = None, model=None):
    """The envs the agents act in: ``POMDPEnv`` of ``num_envs`` on the env group's simulator, truncated at
    ``env.max_steps``. The simulator is the filter's model (``model``, built from ``env.model`` when not
    given) unless ``env.simulator`` names model keys where the two differ: e.g. POPGym's deterministic
    dynamics (``{process_noise: 0.0}``) under a filter that needs process noise.

    With ``env.popgym_task`` the agents act in POPGym's own env instead (TorchRL's ``GymEnv``, a
    ``SerialEnv`` of ``num_envs``; :func:`escort_rl.envs.popgym.make_popgym_env`), which truncates its
    episodes itself and has no ``true_state``."""
    task = cfg.env.get("popgym_task", None)
    if task:
        from torchrl.envs import SerialEnv

        from escort_rl.envs.popgym import make_single_popgym_env, popgym_any_task

        env = SerialEnv(int(num_envs), partial(make_single_popgym_env, popgym_any_task(str(task)), device=cfg.device),
                        device=cfg.device)  # batch [num_envs], as POMDPEnv's, even for one env
        if seed is not None:
            env.set_seed(int(seed))
        return env
    overrides = cfg.env.get("simulator", None)
    if overrides:
        env_cfg = OmegaConf.create(OmegaConf.to_container(cfg.env, resolve=True))
        env_cfg.model = OmegaConf.merge(env_cfg.model, overrides)
        model = build_model(env_cfg, cfg.device, densities=False)
    elif model is None:
        model = build_model(cfg.env, cfg.device)
    return POMDPEnv(model, batch_size=(num_envs,), device=cfg.device, seed=seed, max_steps=cfg.env.max_steps,
                    expose_state=True)  # for the state critic, the metrics and a prior around the start


def trained_action_repeat(cfg: DictConfig) -> int:
    """Env steps per decision of the policy trained by ``cfg``: its trainer's typed
    ``trainer.action_repeat`` (PPO), 1 for a trainer that decides at every step (REINFORCE)."""
    from escort_rl.trainers.algorithm import typed_trainer

    return int(getattr(typed_trainer(cfg), "action_repeat", 1))


def belief_keys(cfg: DictConfig) -> tuple[str, str]:
    """The tensordict keys the belief transform writes and the policies read (``keys.particles``,
    ``keys.log_weights``)."""
    keys = cfg.get("keys") or {}
    return str(keys.get("particles", "particles")), str(keys.get("log_weights", "particle_log_weights"))


def env_factory(cfg: DictConfig, num_envs: int, seed: int | None = None, action_repeat: int = 1):
    """A picklable zero-argument factory for :func:`make_env`."""
    plain = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    return partial(make_env, plain, num_envs, seed, action_repeat)


def input_scaling(cfg: DictConfig, state_dim: int | None = None) -> tuple:
    """The per-dimension standardisation of particles, ``(x − loc) / scale``, of the env group
    (``env.input_loc``, ``env.input_scale``: a number or one per state dimension). With ``state_dim``,
    a list of another length raises :class:`ConfigError` naming the key."""
    def plain(v):
        return OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v

    loc, scale = plain(cfg.env.input_loc), plain(cfg.env.input_scale)
    for key, value in (("input_loc", loc), ("input_scale", scale)):
        if state_dim is not None and isinstance(value, (list, tuple)) and len(value) not in (1, state_dim):
            raise ConfigError(f"env.{key}: expected a number or {state_dim} numbers (one per dimension of the model's "
                              f"state), got {len(value)}; set env.{key} to a number or a list of {state_dim}")
    return loc, scale


def build_critic(cfg: DictConfig, model, critic_input: str) -> tuple:
    """The value network of ``critic_input`` (``trainer.critic_input``) and the keys it reads:
    ``belief``, a :class:`~escort_rl.modules.DeepSetsCritic` on the particles (the actor's sizes and
    input scaling); ``state``, an MLP on the simulator's ``true_state`` (asymmetric actor-critic: only
    training reads it, the policy still acts on the belief)."""
    from escort_rl.modules.critics import StateValueNet

    if critic_input == "state":
        loc, scale = input_scaling(cfg, model.state_dim)
        return StateValueNet(model.state_dim, int(cfg.actor.hidden), loc, scale), ["true_state"]
    return DeepSetsCritic(model.state_dim, **deepsets_sizes(cfg, model.state_dim)), list(belief_keys(cfg))


def build_policy(cfg: DictConfig, model) -> tuple[DeepSetsActor, ProbabilisticActor]:
    """The belief policy of ``model``: a :class:`DeepSetsActor` (:func:`build_actor`) and the TorchRL
    ``ProbabilisticActor`` around it reading ``cfg``'s belief keys: a categorical head for discrete
    actions, a Gaussian put in the action box (``actor.distribution``) for continuous ones
    (:func:`make_deepsets_policy`)."""
    n_outputs, box = policy_outputs(model)
    actor = build_actor(cfg, model.state_dim, n_outputs, model)
    return actor, make_deepsets_policy(actor, *belief_keys(cfg), action_box=box, **continuous_head(cfg))


def continuous_head(cfg: DictConfig) -> dict:
    """The continuous head's ``min_scale`` and ``distribution`` (``actor.min_scale``, ``actor.distribution``); a
    run saved before either key existed loads with what it trained with (TorchRL's floor, a TanhNormal)."""
    return {"min_scale": float(OmegaConf.select(cfg, "actor.min_scale", default=DEFAULT_MIN_SCALE)),
            "distribution": str(OmegaConf.select(cfg, "actor.distribution", default=SAVED_RUN_DISTRIBUTION))}


def deepsets_sizes(cfg: DictConfig, state_dim: int | None = None) -> dict:
    """The keyword arguments of a :class:`~escort_rl.modules.DeepSetsNet` from the ``actor`` group: width
    ``actor.hidden``, depth ``actor.encoder_layers``, ``actor.summary``, ``actor.pooling`` and
    ``actor.attention_heads``, and the env group's input scaling (checked against ``state_dim`` when given) and
    angles (``env.periodic_dims``)."""
    from escort_rl.config.schema import ActorConfig

    actor = OmegaConf.merge(OmegaConf.structured(ActorConfig), cfg.actor)  # typed; a saved config's absent keys
    loc, scale = input_scaling(cfg, state_dim)                              # take the schema's defaults
    periodic = cfg.env.get("periodic_dims", None) or ()  # an env key of the angle-carrying env groups only
    return dict(hidden=actor.hidden, input_loc=loc, input_scale=scale, encoder_layers=actor.encoder_layers,
                periodic_dims=list(periodic), summary=actor.summary, max_particles=actor.max_particles,
                pooling=actor.pooling, attention_heads=actor.attention_heads)


def build_actor(cfg: DictConfig, state_dim: int, n_actions: int, model) -> DeepSetsActor:
    """A :class:`DeepSetsActor` of the ``actor`` group's sizes (:func:`deepsets_sizes`). With
    ``actor.head=per_coordinate`` its outputs come per group of ``model.action_coordinates``; with
    ``auto`` (the default) too where the model declares them, else from the pooled head. A saved config
    without the key (a run from before the heads) has the pooled head."""
    sizes = deepsets_sizes(cfg, state_dim)
    head = OmegaConf.select(cfg, "actor.head", default="pooled")
    groups = getattr(model, "action_coordinates", None)
    if head == "per_coordinate" or (head == "auto" and groups is not None):
        if groups is None:
            raise ConfigError(f"actor.head=per_coordinate: the model {type(model).__name__} declares no "
                              f"action_coordinates (the state coordinates each group of actions acts on); "
                              f"use actor.head=pooled, or give the model that attribute")
        layout = "output_major" if is_continuous(model) else "group_major"
        hidden = OmegaConf.select(cfg, "actor.group_hidden", default=16)
        sizes.update(coordinate_groups=tuple(groups), group_layout=layout, group_hidden=int(hidden))
    return DeepSetsActor(state_dim, n_actions, **sizes)


def scripted_gain(cfg) -> float:
    """The scripted controller's velocity gain for ``cfg``'s env: ``env.scripted_gain`` (the best of a
    sweep, stored in the env group), else the controller's default (also for a config saved before
    the key existed)."""
    gain = OmegaConf.select(cfg, "env.scripted_gain", default=None)
    return DEFAULT_GAIN_V if gain is None else float(gain)


def teacher_gain(cfg) -> float:
    """The kickstart teacher's velocity gain for ``cfg``'s env: ``env.teacher_gain`` where the env group sets
    one (the gain the measured default job learned from), else :func:`scripted_gain`."""
    gain = OmegaConf.select(cfg, "env.teacher_gain", default=None)
    return scripted_gain(cfg) if gain is None else float(gain)


def controller_options(cfg, role: str = "scripted") -> tuple[dict, str]:
    """The scripted controller's keyword options beyond its gain, and the config key they came from: for the
    evaluation's controller (``role="scripted"``) ``env.scripted_options``; for the kickstart teacher
    (``role="teacher"``) ``env.teacher_options``, else the evaluation's. E.g. the hidden goal's look-first rule,
    ``{confidence: 0.9}``; none: ``{}``."""
    if role not in ("scripted", "teacher"):
        raise ValueError(f"controller_options: role must be 'scripted' or 'teacher', got {role!r}")
    keys = ["env.teacher_options", "env.scripted_options"] if role == "teacher" else ["env.scripted_options"]
    for key in keys:
        options = OmegaConf.select(cfg, key, default=None)
        if options is not None:
            return (dict(OmegaConf.to_container(options)) if OmegaConf.is_config(options) else dict(options)), key
    return {}, keys[-1]


def scripted_policy(cfg, model, action_key: str = "action", gain_v: float | None = None,
                    on_true_state: bool = False, role: str = "scripted"):
    """The domain's scripted controller at velocity gain ``gain_v`` (default :func:`scripted_gain`) on the
    belief of ``cfg``'s filter (``on_true_state``: on the simulator's ``true_state`` instead, which only a
    training env exposes), writing ``action_key``, or ``None`` where the domain has none (Kidnapped Robot:
    no goal to drive to). Its options beyond the gain are :func:`controller_options` of ``role``
    (:func:`~escort_rl.planners.scripted.scripted_controller_for`); options it does not take raise a
    ``ConfigError`` naming the key they came from."""
    options, options_key = controller_options(cfg, role)
    gain_v = scripted_gain(cfg) if gain_v is None else gain_v
    controller = None
    if options:
        try:
            controller = scripted_controller_for(model, gain_v, **options)
        except ValueError as err:
            raise ConfigError(f"{options_key}: {err}") from None
    try:
        if on_true_state:
            return TrueStateController(model, action_key=action_key, gain_v=gain_v, controller=controller)
        particles_key, log_weights_key = belief_keys(cfg)
        return ScriptedBeliefController(model, particles_key=particles_key, log_weights_key=log_weights_key,
                                        action_key=action_key, gain_v=gain_v, controller=controller)
    except ValueError:
        return None
