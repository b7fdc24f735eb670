"""Every setting of one ``bench headline`` run in a frozen :class:`HeadlineSpec`, with ``quick()``
(``--quick``); the field defaults are the full run, and this module is the only place that states a
default."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

DEFAULT_OUTPUT = "outputs/bench/headline"
"""``bench headline``'s ``--output``."""

TRAINED_ROWS = (
    ("default job (kickstarted; SIR warm start, then ESCORT)", ()),
    ("PPO on SIR beliefs only, 16 iterations", ("filter=sir_rough", "trainer.warm_start_iterations=0",
                                                "trainer.iterations=16")),
)
"""The trained rows: a label and the overrides on top of the default job. The SIR-only row trains on the
default job's warm-start filter (``sir_rough``) for 16 iterations (512,000 frames), twice the default job's
frames: SIR's frames are cheap, and the row asks what the learner reaches, not what it reaches at equal cost."""

SIXTEEN_ITERATION_JOB = ("trainer.iterations=16", "trainer.warm_start_iterations=8")
"""The default job before it was halved to fit its 10 minutes on the slower of our 2-core machines: 8 iterations
on SIR beliefs, then 8 on ESCORT's (512,000 frames). The row sets measured on it keep it."""

EARLIER_JOB = ("actor.head=pooled", "trainer.iterations=33", "trainer.warm_start_iterations=30", "trainer.teacher=none")
"""The default job before the per-coordinate head: the pooled head, 30 iterations on SIR beliefs, then 3 on
ESCORT's (1.06M frames). The row sets below measured changes to it, and keep it so that they still do (with no
teacher, as then)."""


def _on_earlier_job(*overrides: str) -> tuple[str, ...]:
    """``overrides`` on top of :data:`EARLIER_JOB` (a key they set replaces the job's)."""
    own = {o.split("=", 1)[0] for o in overrides}
    return (*(o for o in EARLIER_JOB if o.split("=", 1)[0] not in own), *overrides)


ABLATION_ROWS = (
    ("PPO on SIR beliefs (as shipped)", _on_earlier_job("filter=sir_rough", "trainer.warm_start_iterations=0")),
    ("+ belief summary to the actor", _on_earlier_job("filter=sir_rough", "trainer.warm_start_iterations=0",
                                                      "actor.summary=true")),
    ("default job (as shipped)", _on_earlier_job()),
    ("default job, 8 epochs in the warm start too", _on_earlier_job("trainer.warm_start_epochs=null")),
    ("default job + belief summary", _on_earlier_job("actor.summary=true")),
)
"""``--rows ablation``: the learner's changes one at a time, on SIR beliefs (the learner alone, no belief
shift) and on the default job (SIR warm start, then ESCORT). PPO on SIR beliefs only runs 8 epochs per batch
throughout (no warm start), the default job 4 in its warm start: the second default-job row removes that
difference."""

START_ROWS = (
    ("default job (as shipped)", _on_earlier_job()),
    ("default job, half the training starts in the evaluation's box",
     _on_earlier_job("env.exploring_starts.paper_start_share=0.5")),
)
"""``--rows starts``: the default job's exploring starts (uniform in ``[0, 10]^5``, on average half as far
from the goal as the evaluation's ``[0, 2]^5``) against the same with half the training episodes
starting in the evaluation's box."""

HALF_ROWS = (
    ("half on ESCORT: 12 + 12 iterations, linear lr, 50-step batches",
     _on_earlier_job("trainer.iterations=24", "trainer.warm_start_iterations=12", "trainer.lr_schedule=linear",
                     "trainer.rollout_steps=50")),
)
"""``--rows half``: a job that trains half its frames on ESCORT beliefs (12 iterations on SIR beliefs, then
12 on ESCORT's: 768,000 frames), with the learning rate falling linearly and 3,200-frame batches (two and a
half times the Adam steps per frame), so that ESCORT's dear frames teach more."""

FRAMES_ROWS = (
    ("PPO on SIR beliefs, 45 iterations", _on_earlier_job("filter=sir_rough", "trainer.warm_start_iterations=0",
                                                          "trainer.iterations=45")),
)
"""``--rows frames``: PPO on SIR beliefs for 1.44M frames, 36% more than the earlier default job's; with
``--curve-every``, success against frames."""

COORDINATE_ROWS = (
    ("PPO on SIR beliefs, per-coordinate head", ("filter=sir_rough", "trainer.warm_start_iterations=0",
                                                 "actor.head=per_coordinate", "trainer.iterations=33",
                                                 "trainer.teacher=none")),
    ("per-coordinate head, 8 SIR + 8 ESCORT iterations", ("actor.head=per_coordinate", "trainer.iterations=16",
                                                          "trainer.warm_start_iterations=8", "trainer.teacher=none")),
    ("per-coordinate head, 8 + 8 iterations, linear lr", ("actor.head=per_coordinate", "trainer.iterations=16",
                                                          "trainer.warm_start_iterations=8",
                                                          "trainer.lr_schedule=linear", "trainer.teacher=none")),
)
"""``--rows coordinates``: the policy's outputs from one network shared by the action groups
(``actor.head=per_coordinate``: each pair of pushes scored from its own coordinate's particles and the
pooled belief), on SIR beliefs for 33 iterations (1.06M frames, the earlier default job's), and in a job of
half as many frames with half of them on ESCORT beliefs (8 iterations on SIR beliefs, then 8 on ESCORT's:
512,000 frames; the default job until it was halved), with a constant and a linearly falling learning rate."""

OWN_FILTER_ROWS = (
    ("ESCORT beliefs only, 16 iterations", ("trainer.iterations=16", "trainer.warm_start_iterations=0",
                                            "trainer.teacher=none")),
)
"""``--rows own_filter``: the 16-iteration job's iterations (512,000 frames) all on its own filter's beliefs, with no
SIR warm start, so that the policy never meets the shift from SIR's beliefs to ESCORT's."""

HORIZON_ROWS = (
    ("16-iteration job, gamma 0.995", (*SIXTEEN_ITERATION_JOB, "trainer.gamma=0.995", "trainer.teacher=none")),
    ("16-iteration job, entropy 0.003", (*SIXTEEN_ITERATION_JOB, "trainer.entropy_coef=0.003",
                                         "trainer.teacher=none")),
)
"""``--rows horizon``: the 16-iteration job (:data:`SIXTEEN_ITERATION_JOB`) with a discount that reaches past
100 decisions (γ = 0.995: about 200), and with a smaller entropy bonus, so that the policy that hovers near the
goal in the dark sees the cost of not finishing, or settles on one action there."""

TEACHER_ROWS = (
    ("16-iteration job, teacher over the warm start only", (*SIXTEEN_ITERATION_JOB, "trainer.kickstart_iterations=8")),
    ("16-iteration job without a teacher", (*SIXTEEN_ITERATION_JOB, "trainer.teacher=none")),
)
"""``--rows teacher``: the 16-iteration job's (:data:`SIXTEEN_ITERATION_JOB`) kickstart (the scripted controller
as a teacher: each Adam step also minimises the policy's cross-entropy to the controller's action on the same
belief, with a weight falling from 1 to 0 over the whole run) against a weight that reaches 0 at the end of the SIR
warm start, and against no teacher (the default job before)."""

REINFORCE_ROWS = (
    ("REINFORCE on SIR beliefs, learned baseline, 4x the frames", (
        "trainer=reinforce", "filter=sir_rough", "trainer.exploring_starts=true", "trainer.baseline=learned",
        "trainer.iterations=256")),
)
"""``--rows reinforce``: the paper's own learner, REINFORCE with an entropy bonus, as a user of the paper would tune
it: a learned baseline (a DeepSets critic), returns scaled and advantages standardised per batch, the exploring
starts and the per-coordinate head PPO uses, 16 full episodes (8,000 frames) per step, on SIR beliefs for 256
steps: 2.05M frames, four times the 16-iteration job's. A pilot at 64 steps (512,000 frames, one seed) reached the goal
in 19% of the evaluation's episodes, still climbing."""

MTT_ROWS = (
    ("PPO on SIR beliefs (40 iterations of 100-step batches)", (
        "filter=sir_rough", "trainer.warm_start_iterations=0", "trainer.rollout_steps=100", "trainer.iterations=40")),
)
"""``--rows mtt`` (with ``env=mtt20d``): PPO on SIR beliefs on Multi-Target Tracking 20D as first measured there
(64 envs × 200 steps an iteration, 512,000 frames, two PPO batches of 100 steps each), on today's learner, beside
the controller's velocity gain swept on the same filters."""

def frontier_rows(path: str | Path, budget_ms: float) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """``--frontier-rows PATH MS``: a trained row (PPO, no warm start) on each filter's configuration that a
    frontier (``frontier.json`` of ``bench frontier``) found closest to its reference within ``MS`` ms an
    update: equal filter time."""
    from escort_rl.bench.frontier.run import budget_configurations

    return tuple((f"PPO on {name} (closest within {budget_ms:g} ms)", (*overrides, "trainer.warm_start_iterations=0"))
                 for name, overrides in budget_configurations(path, budget_ms, "--frontier-rows"))


ROW_SETS = {"headline": TRAINED_ROWS, "default": TRAINED_ROWS[:1], "ablation": ABLATION_ROWS, "starts": START_ROWS,
            "half": HALF_ROWS,
            "frames": FRAMES_ROWS, "coordinates": COORDINATE_ROWS, "own_filter": OWN_FILTER_ROWS,
            "horizon": HORIZON_ROWS, "teacher": TEACHER_ROWS,
            "reinforce": REINFORCE_ROWS, "mtt": MTT_ROWS}
"""The trained rows ``--rows`` picks by name."""

SCRIPTED_FILTERS = ("escort_train", "sir_rough")
"""The beliefs the scripted controller acts on: each trained row's filter (for the named row sets)."""

_QUICK = dict(seeds=2, episodes=4, gains=(1.0, 3.0),
              overrides=("trainer.iterations=2", "trainer.warm_start_iterations=1", "trainer.num_envs=4",
                         "trainer.rollout_steps=16", "trainer.minibatches=2", "trainer.epochs=2", "env.max_steps=20",
                         "num_particles=16", "actor.hidden=16", "filter.compile=false"))
"""What ``bench headline --quick`` changes: 2 seeds of a tiny job (2 iterations, 20-step episodes)."""


@dataclass(frozen=True)
class HeadlineSpec:
    """The headline RL table: each trained row over ``seeds`` training seeds (each evaluated greedily
    on the same ``episodes`` episodes), the scripted controller at its best gain on each row's belief
    and a uniform-random policy.

    The gain is chosen among ``gains`` on ``selection_episodes`` other episodes (``None``: as many as the
    table's ``episodes``; env seeds from ``selection_seed``), then evaluated on the table's episodes (from
    ``eval_seed``), so that the choice does not select on the reported noise. The controller's action (push the
    dimension of the largest ``|k_p·(g − x̂) − k_v·v̂|``) depends on the gains through ``k_v / k_p`` alone, so the grid of
    velocity gains at ``k_p = 1`` sweeps both; 0 is a pure P rule. ``scripted_filters``: the beliefs the
    controller acts on, each a filter config name or the overrides that pick the belief, space-separated
    (``"filter=sir num_particles=3000"``); ``None``: each belief a trained row acts on. A trained row is paired,
    episode by episode, with the controller on the same belief (filter and particle count).
    ``overrides`` go under every row's own (the
    smoke run's sizes); ``threads``: torch threads per cell; ``curve_every = k > 0``: every trained seed
    also evaluates its checkpoint of every ``k``-th iteration on the same episodes (success against
    frames, beside the controller's line).

    Examples:
        >>> HeadlineSpec().seeds, HeadlineSpec.quick().seeds
        (5, 2)
        >>> HeadlineSpec(seeds=0)
        Traceback (most recent call last):
        ...
        ValueError: --seeds: must be >= 1, got 0
    """

    seeds: int = 5
    episodes: int = 100
    eval_seed: int = 10000
    selection_seed: int = 20000
    selection_episodes: int | None = None
    gains: tuple[float, ...] = (0.0, 0.125, 0.25, 0.5, 1.0, 2.0, 3.0)
    rows: tuple[tuple[str, tuple[str, ...]], ...] = TRAINED_ROWS
    scripted_filters: tuple[str, ...] | None = SCRIPTED_FILTERS
    overrides: tuple[str, ...] = ()
    threads: int = 1
    curve_every: int = 0
    output: Path = Path(DEFAULT_OUTPUT)

    def __post_init__(self) -> None:
        for flag, value in (("--seeds", self.seeds), ("--episodes", self.episodes), ("--threads", self.threads),
                            ("--selection-episodes", self.selection_size)):
            if int(value) < 1:
                raise ValueError(f"{flag}: must be >= 1, got {value}")
        if int(self.curve_every) < 0:
            raise ValueError(f"--curve-every: give 0 (no curve) or an iteration count >= 1, got {self.curve_every}")
        if not self.gains or any(float(g) < 0 for g in self.gains):
            raise ValueError(f"--gains: give one or more velocity gains >= 0, got {list(self.gains)}")
        object.__setattr__(self, "gains", tuple(float(g) for g in self.gains))
        object.__setattr__(self, "overrides", tuple(self.overrides))
        if self.scripted_filters is not None:
            from escort_rl.bench.headline.cells import check_belief

            object.__setattr__(self, "scripted_filters", tuple(self.scripted_filters))
            for belief in self.scripted_filters:
                check_belief(belief)
        if not self.rows:
            raise ValueError("--row: give at least one trained row")
        object.__setattr__(self, "output", Path(self.output))

    @property
    def selection_size(self) -> int:
        """The gain search's episodes: ``selection_episodes``, else ``episodes``.

        Examples:
            >>> HeadlineSpec(episodes=500).selection_size, HeadlineSpec(selection_episodes=100).selection_size
            (500, 100)
        """
        return int(self.episodes if self.selection_episodes is None else self.selection_episodes)

    @classmethod
    def quick(cls, **changes) -> HeadlineSpec:
        """``--quick``: :data:`_QUICK` with ``changes`` on top."""
        return cls(**{**_QUICK, **changes})

    def replace(self, **changes) -> HeadlineSpec:
        return dataclasses.replace(self, **changes)
